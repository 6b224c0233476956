"""A real arm takes the sim's place with no code of ours changed: a stand-in written against
the ROS 2 message types alone (``standin_arm.py``) follows the gate's JointTrajectory and
reports JointState, and the pipeline runs with it."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import yaml

from wavegrasp.arm import ArmModel
from wavegrasp.recording_io.mcap_read import read_mcap
from wavegrasp.recording_io.ros_msgs import decode_joint_state, decode_joint_trajectory

from conftest import ROOT, make_recording, own_messages, wavegrasp_cmd

ARM_TOPIC = "/arm/joint_trajectory_controller/joint_trajectory"


def standin_compose(path: Path, arm: ArmModel) -> Path:
    """docker-compose.yml with the sim replaced by the stand-in arm."""
    compose = yaml.safe_load((ROOT / "docker-compose.yml").read_text())
    services = compose["services"]
    sim = services.pop("sim")
    fingers = [arm.joints[n] for n in arm.jaw_joints]
    services["arm"] = {
        "image": sim["image"], "depends_on": sim["depends_on"],
        "environment": {"ZENOH_CONNECT": sim["environment"]["ZENOH_CONNECT"]},
        "command": [sys.executable, str(ROOT / "tests" / "standin_arm.py"),
                    "--joints", ",".join(arm.joint_names),
                    "--home", ",".join(f"{q:.9f}" for q in arm.q_home),
                    "--fingers", ",".join(arm.jaw_joints), "--open", str(fingers[0].upper)]}
    player = services["player"]
    player["depends_on"].pop("sim")
    for name in ("WAVEGRASP_ACK_SERVICES", "WAVEGRASP_WAIT_FOR"):  # the sim's, not the arm's
        player["environment"][name] = ",".join(
            s for s in player["environment"][name].split(",") if s != "sim")
    player["environment"]["WAVEGRASP_ROS_CLOCK_KEY"] = "clock"  # the stand-in's use_sim_time
    path.write_text(yaml.safe_dump(compose))
    return path


def test_a_standin_arm_takes_the_sims_place(tmp_path: Path) -> None:
    arm = ArmModel.load()
    rec = make_recording(tmp_path / "can.mcap", seconds=18.0, seed=2, wave=2, object="can_empty")
    out = tmp_path / "run"
    result = subprocess.run(wavegrasp_cmd(
        "up", str(rec), "--pace", "realtime", "--out", str(out),
        "--compose", str(standin_compose(tmp_path / "compose.yml", arm))),
        capture_output=True, text=True, timeout=240)
    assert result.returncode == 0, result.stdout[-3000:]
    assert "stand-in arm: took" in result.stdout, result.stdout[-3000:]
    run = out / "run.mcap"
    paths, states = [], []
    for _schema, channel, message in read_mcap(run, [ARM_TOPIC, "/joint_states"]):
        if channel.topic == ARM_TOPIC:
            paths.append(decode_joint_trajectory(message.data))
        else:
            states.append(decode_joint_state(message.data))
    decisions = own_messages(run, "wavegrasp/gate/decision")
    assert any(d["go"] for d in decisions), [d["reason"] for d in decisions]
    assert paths, "no trajectory went to the arm's controller"
    assert len(states) >= 150  # one a clock tick, from the stand-in
    n = len(arm.joint_names)
    # The stand-in followed the first commanded path (its samples, as the planner made them).
    names, times, q, _qd = paths[0]
    assert names == list(arm.joint_names)
    on_path = [s for s in states if times[0] <= s[0] * 1e-9 <= times[-1]]
    assert len(on_path) >= 10
    for stamp_ns, _names, positions, _velocities in on_path:
        expected = [np.interp(stamp_ns * 1e-9, times, q[:, j]) for j in range(n)]
        np.testing.assert_allclose(positions[:n], expected, atol=1e-6)
    # Plans made after that path ended start where the stand-in said it was.
    plans = [p for p in own_messages(run, "wavegrasp/planner/plan")
             if p["joint_trajectory"] and p["header"]["stamp_ns"] * 1e-9 > times[-1] + 0.2
             and p["update_of"] is None]
    for plan in plans:
        before = [s for s in states if s[0] <= plan["header"]["stamp_ns"]]
        np.testing.assert_allclose(plan["joint_trajectory"][0]["positions"], before[-1][2][:n],
                                   atol=1e-3)
    summary = json.loads((out / "summary.json").read_text())
    assert summary["bad_messages"] == {}  # the stand-in's JointState, bridge-like, all taken
    assert "sim" not in summary["services"] and summary["services"]["gate"]["counters"]["go"]

"""``wavegrasp up --tether MBIT``: the vehicle's services in a network namespace of their own,
joined to the topside's by a shaped veth pair, router to router; the edge stage's clouds cross
it within the link, the run grasps across it, and it survives the tether's cuts."""

from __future__ import annotations

import json
import os
import subprocess
from pathlib import Path

import pytest

from wavegrasp.recording_io.reader import open_recording, read_mcap
from wavegrasp.recording_io.ros_msgs import decode_points

from conftest import make_recording, wavegrasp_cmd

pytestmark = pytest.mark.skipif(os.geteuid() != 0, reason="network namespaces need root")


def test_a_run_across_a_tether_grasps_and_the_clouds_fit_the_link(tmp_path: Path) -> None:
    rec = make_recording(tmp_path / "can.mcap", seconds=16.0, seed=3, wave=2, object="can_half")
    out = tmp_path / "run"
    result = subprocess.run(wavegrasp_cmd("up", str(rec), "--tether", "20", "--out", str(out)),
                            capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, result.stdout[-3000:]
    assert "network namespace" in result.stdout
    summary = json.loads((out / "summary.json").read_text())
    assert summary["exit_codes"]["vehicle-router"] == 0 and summary["exit_codes"]["edge"] == 0
    assert summary["outcomes"] and summary["outcomes"][0]["success"], summary["outcomes"]
    assert not summary["bad_messages"]
    row = next(line for line in result.stdout.splitlines() if line.startswith("      1  "))
    assert "success" in row and "mm (ε 10)" in row, row  # the run's table: the attempt
    # The recorder subscribes to everything, yet the camera's full clouds stayed on the
    # vehicle: the edge stage's crossed instead, one for every camera frame, with the frame's
    # own sequence number and stamp, and a third of its points or fewer.
    sources = [m for m in open_recording(rec).messages() if m.topic == "/trisect/points"]
    edge = [(message.sequence, decode_points(message.data)) for _, _, message in
            read_mcap(out / "run.mcap", topics=["/wavegrasp/edge/points", "/trisect/points"])]
    assert [seq for seq, _ in edge] == list(range(len(sources)))
    assert [c.stamp_ns for _, c in edge] == [m.log_time_ns for m in sources]
    kept = sum(len(c.points) for _, c in edge) / sum(len(decode_points(m.cdr).points)
                                                     for m in sources)
    assert 0.05 < kept < 0.34, kept
    counters = summary["services"]["edge"]["counters"]
    assert counters["frames"] == len(sources) and counters["frames with a region"] > 100
    # Within the link: the clouds at 0.4 of it, the rest a few per cent more.
    traffic = summary["tether"]
    assert traffic["mbit"] == 20
    assert 4 < traffic["up_mean_mbit_s"] < 20 * 0.5 and traffic["up_peak_mbit_s"] < 20
    assert 0 < traffic["down_mean_mbit_s"] < 5
    names = subprocess.run(["ip", "netns", "list"], capture_output=True, text=True).stdout
    assert "wgt" not in names  # the namespace went with the run


def test_tether_cuts_stop_the_arm_and_the_run_recovers_to_a_grasp(tmp_path: Path) -> None:
    rec = make_recording(tmp_path / "buoy.mcap", seconds=40.0, seed=0, wave=1, object="buoy")
    out = tmp_path / "faults"
    result = subprocess.run(wavegrasp_cmd("faults", str(rec), "--tether", "20", "--out",
                                          str(out)), capture_output=True, text=True, timeout=600)
    report = json.loads((out / "faults.json").read_text())
    cuts = {f["target"]: f for f in report["faults"] if f["kind"] == "tether cut"}
    assert set(cuts) == {"during an approach", "while idle"}, result.stdout[-3000:]
    for cut in cuts.values():
        # Stopped on the watchdog (0.5 s and a check every 50 ms), everyone back on their own.
        assert cut["survived"], cut
        stopped_ms = int(cut["lost"].split("arm stopped ")[1].split(" ms")[0])
        assert 500 <= stopped_ms <= 600, cut
        assert cut["back_after_s"] < 10
    outcomes = json.loads((out / "summary.json").read_text())["outcomes"]
    # The approach cut off (the plan the arm was executing) ended aborted by the watchdog;
    # a later one grasped.
    plan = cuts["during an approach"]["detail"].removeprefix("plan ")
    (cut_off,) = [o for o in outcomes if o["plan_id"] == plan]
    assert cut_off["aborted"] and "no heartbeat" in cut_off["evidence"]["reason"], outcomes
    assert outcomes[-1]["success"], outcomes
    assert result.returncode == 0, result.stdout[-3000:]


def test_a_tether_needs_a_bandwidth(tmp_path: Path) -> None:
    done = subprocess.run(wavegrasp_cmd("up", "--tether", "0", "--out", str(tmp_path)),
                          capture_output=True, text=True, timeout=60)
    assert done.returncode == 2 and "--tether 0: the bandwidth must be > 0" in done.stderr

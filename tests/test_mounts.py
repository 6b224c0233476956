"""The pipeline end to end with the arm mounted where the paper's tank never put it: across
the swing, on the far side of the swing plane, turned away from the object. Each runs every
service as a process over zenoh in lockstep and must grasp."""

from __future__ import annotations

import json
import subprocess
from pathlib import Path

import pytest

from wavegrasp.wavetank.record import generate
from wavegrasp.wavetank.scenario import paper_scenario
from wavegrasp.wavetank.suite import mount_at

from conftest import own_messages, wavegrasp_cmd

#: (name, object, bearing from the object in degrees (0: the way the waves run), the
#: shoulder's rise above the object, the mount's turn away from facing it in degrees, the
#: camera's cloud: the second is organized, as a stereo driver publishes it; the wave period,
#: s, where not wave 2's: 0.8 s waves are forecast 2.8 s ahead, too little for an arm facing
#: away to turn and reach the object).
MOUNTS = [("sideways-turned-away", "can_half", -90.0, -0.05, 90.0, "dense", None),
          ("behind-the-swing-plane", "buoy", 120.0, -0.1, -45.0, "organized", None),
          ("facing-away", "can_half", 20.0, -0.05, 170.0, "dense", 0.8)]


@pytest.mark.parametrize("name, obj, bearing, rise, yaw, cloud, period", MOUNTS,
                         ids=[m[0] for m in MOUNTS])
def test_an_arm_mounted_elsewhere_grasps(tmp_path: Path, name: str, obj: str, bearing: float,
                                         rise: float, yaw: float, cloud: str,
                                         period: float | None) -> None:
    base = paper_scenario(2, obj)
    scenario = paper_scenario(2, obj, name=name, seconds=24.0, seed=5,
                              mount=mount_at(base.rest, 0.6, bearing, rise, yaw),
                              camera=base.camera.model_copy(update={"cloud": cloud}),
                              sea=base.sea.model_copy(update={"period_s": period or
                                                              base.sea.period_s}))
    rec = tmp_path / f"{name}.mcap"
    generate(scenario, rec)
    out = tmp_path / "run"
    env_cmd = wavegrasp_cmd("up", str(rec), "--pace", "lockstep", "--out", str(out))
    result = subprocess.run(env_cmd, capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, result.stdout[-3000:]
    summary = json.loads((out / "summary.json").read_text())
    outcomes = own_messages(out / "run.mcap", "wavegrasp/sim/outcome")
    plans = own_messages(out / "run.mcap", "wavegrasp/planner/plan")
    assert plans, f"no plan: {summary.get('counters', {}).get('planner')}"
    # The arm waits facing the object, not where its mount points; one that starts facing
    # away is moved there before its first plan.
    assert all(p["standby"] for p in plans)
    if abs(yaw) > 120:
        counters = {name: s["counters"] for name, s in summary["services"].items()}
        assert counters["planner"].get("standby moves", 0) >= 1, counters["planner"]
        assert counters["gate"].get("standby moves", 0) >= 1, counters["gate"]  # commanded
    assert any(o["success"] for o in outcomes), outcomes
    # Replayed on the run's own messages, the planner plans as it did in the run.
    replayed = subprocess.run(wavegrasp_cmd("replan", str(out)),
                              capture_output=True, text=True, timeout=300)
    assert replayed.returncode == 0, replayed.stderr[-3000:]
    row = replayed.stdout.splitlines()[-1].split("|")
    planner = summary["services"]["planner"]["counters"]
    assert [int(row[3]), int(row[4])] == [planner.get("plans", 0), planner.get("no plan", 0)]

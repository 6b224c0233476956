"""``wavegrasp faults``: every service killed with SIGKILL during a realtime run comes back,
bad input on every key is counted, bad files are named, and the gate approves nothing while
an upstream service is down."""

from __future__ import annotations

import json
import subprocess
from pathlib import Path

from wavegrasp.ops import launcher as up
from wavegrasp.ops.faults import BACK_WITHIN_S, KILL_ORDER, Down, Fault, Injector

from conftest import make_recording, wavegrasp_cmd


def test_every_fault_is_survived(tmp_path: Path) -> None:
    recording = make_recording(tmp_path / "tank.mcap", seconds=30.0, seed=5, wave=2,
                               object="can_empty")
    out = tmp_path / "run"
    result = subprocess.run(wavegrasp_cmd("faults", str(recording), "--out", str(out),
                                          "--pause-s", "0.5"),
                            capture_output=True, text=True, timeout=240)
    assert result.returncode == 0, result.stdout[-4000:] + result.stderr[-2000:]
    faults = json.loads((out / "faults.json").read_text())["faults"]
    summary = json.loads((out / "summary.json").read_text())
    assert summary["ended"] == "finished" and not summary["crashed"]
    killed = {f["target"]: f for f in faults if f["kind"] == "SIGKILL"}
    assert list(killed) == KILL_ORDER, "every service was killed during the run"
    for name, fault in killed.items():
        assert fault["survived"] and fault["back_after_s"] <= BACK_WITHIN_S, fault
        (restart,) = summary["restarts"][name]
        assert restart["exit_code"] == -9 and restart["back_s"] is not None
    (gate,) = [f for f in faults if f["kind"] == "gate while upstream down"]
    assert gate["survived"] and gate["lost"].startswith("0 plans approved"), gate
    (bad,) = [f for f in faults if f["kind"] == "bad input"]
    assert bad["survived"] and "all counted as bad" in bad["lost"], bad
    # Counts add up across restarts: perception counted each bad camera frame.
    assert summary["bad_messages"]["perception"]["trisect/points"] >= 5
    files = [f for f in faults if f["kind"] == "bad file"]
    assert len(files) == 3 and all(f["survived"] for f in files), files
    assert summary["player"]["frames"] == 300, "the player resumed, no frame replayed twice"
    assert f"{len(faults)} of {len(faults)} faults survived" in result.stdout
    # The killed recorder's file and its successor's are both there and readable; of what it
    # had written, at most a second was lost.
    assert summary["files"] == ["run-1.mcap", "run.mcap"]
    assert killed["recorder"]["lost_s"] <= 1.0, killed["recorder"]


def test_a_service_not_back_when_the_run_ends_is_judged_lost(tmp_path: Path) -> None:
    """On a slow machine the run can end while a killed service is still down: that kill
    is not survived, the plans approved meanwhile count against the gate, and the report is
    still written (it was a crash of the tool itself: a kill without its time down)."""
    recording = Path(__file__).parents[1] / "recordings" / "wave1-buoy-5s.mcap"
    run = up.prepare(up.parse_args([str(recording), "--out", str(tmp_path / "run")]))
    injector = Injector(run, ["planner", "sim"], 0.5)
    back = Fault("SIGKILL", "planner", 1.0, back_after_s=0.9)
    lost = Fault("SIGKILL", "sim", 3.0)
    injector.faults += [back, lost]
    injector.down += [Down("planner", back, 100.0, 100.9), Down("sim", lost, 102.0)]
    injector.watch.gos.append(100.5)  # while the planner was down
    injector.settle({"ended": "finished", "player": {"frames": 50}})
    assert back.survived and not lost.survived
    assert lost.detail == "not back when the run ended"
    (gate,) = [f for f in injector.faults if f.kind == "gate while upstream down"]
    assert not gate.survived and gate.lost.startswith("1 plans approved"), gate

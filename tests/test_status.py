"""What a run shows: its status line and, at the end, its table."""

from __future__ import annotations

from pathlib import Path

from wavegrasp.ops.status import Progress
from wavegrasp.recorder.summary import RunSummary
from wavegrasp.runtime.trace import new_header
from wavegrasp.schemas import Clock, GateDecision, GraspOutcome, Header, Hop, ServiceStats


def decision(plan_id: str, go: bool, reason: str, latency_ms: float) -> GateDecision:
    trace = [Hop(service="source", recv_ns=10**9, sent_ns=10**9),
             Hop(service="gate", recv_ns=10**9, sent_ns=10**9 + int(latency_ms * 1e6))]
    return GateDecision(header=Header(stamp_ns=1, trace=trace), plan_id=plan_id, go=go,
                        mean_error_m=0.0042, threshold_m=0.01, window_s=1.0, reason=reason)


def test_the_status_line_and_the_table_say_what_the_run_came_to(tmp_path: Path) -> None:
    progress = Progress(start_ns=10**9, end_ns=61 * 10**9)
    summary = RunSummary()
    progress.on_clock(Clock(header=new_header("player", 1, 13 * 10**9),
                            published={"trisect/points": 120}))
    summary.on_stats(ServiceStats(header=new_header("perception", 1, 0), service="perception",
                                  counters={"observed": 118}, uptime_s=1.0))
    for i, (plan, go, reason) in enumerate([("1-a", False, "error"), ("2-a", True, "go"),
                                            ("3-a", True, "go: update")]):
        progress.on_decision(decision(plan, go, reason, 40.0 + 10 * i))
    summary.on_outcome(GraspOutcome(header=new_header("sim", 1, 0), plan_id="2-a", trial=0,
                                    attempt=1, success=True))
    line = progress.line(summary)
    assert line.startswith("12.0 / 60.0 s | frames 120 | observed 118 | predictions 0")
    assert "go 2 / no-go 1 | grasps 1 of 1 | latency p50 50 ms" in line
    out = tmp_path / "x"
    out.mkdir()
    (out / "run.rrd").write_bytes(b"")
    table = progress.table(summary, {"perception": 1}, out).splitlines()
    assert table[1].split() == ["1", "success", "4.2", "mm", "(ε", "10)", "2-a"]
    assert table[2].startswith("gate: 1 plans and 1 updates approved, 1 refused; "
                               "latency p50 / p99 50 / 60 ms")
    assert table[2].endswith("bad messages 0; restarts perception 1")
    assert table[3].startswith(f"see it: rerun {out / 'run.rrd'}  |  Foxglove: open")

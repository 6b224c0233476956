"""What a run shows while it goes and when it ends: one status line (recording time of its
total, frames, observed, predictions, plans, go / no-go, grasps, latency p50) and a table of
each grasp attempt with what the run came to.

Fed from the launcher's own session: the players' clock, the gate's decisions and the
services' stats (:class:`~wavegrasp.recorder.summary.RunSummary`).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from wavegrasp.recorder.summary import RunSummary
from wavegrasp.schemas import Clock, GateDecision

UPDATE_REASON = "go: update"
CAMERA_KEY = "trisect/points"


@dataclass
class Decision:
    """A gate decision as the table needs it: the plan, go, an update's or a plan's, the
    error against ε, millimetres, and the camera-to-decision latency, milliseconds."""

    plan_id: str
    go: bool
    update: bool
    error_mm: float | None
    threshold_mm: float
    latency_ms: float | None


@dataclass
class Progress:
    """A run's progress. ``start_ns`` and ``end_ns``: the recording's first and last log
    time (None: unknown, the total is not shown)."""

    start_ns: int | None = None
    end_ns: int | None = None
    now_ns: int | None = None
    frames: int = 0  # camera frames the player has published, by its clock's count
    decisions: list[Decision] = field(default_factory=list)

    def on_clock(self, msg: Clock) -> None:
        self.now_ns = msg.header.stamp_ns
        self.frames = msg.published.get(CAMERA_KEY, self.frames)

    def on_decision(self, msg: GateDecision) -> None:
        trace = msg.header.trace
        latency = None
        if len(trace) >= 2 and trace[-1].sent_ns and trace[0].recv_ns:
            latency = (trace[-1].sent_ns - trace[0].recv_ns) / 1e6
        self.decisions.append(Decision(
            msg.plan_id, msg.go, msg.reason == UPDATE_REASON,
            None if msg.mean_error_m is None else msg.mean_error_m * 1e3,
            msg.threshold_m * 1e3, latency))

    def latency_ms(self, q: float) -> float | None:
        values = [d.latency_ms for d in self.decisions if d.latency_ms is not None]
        return float(np.percentile(values, q)) if values else None

    def line(self, summary: RunSummary) -> str:
        """The status line: ``12.3 / 60.0 s | frames 123 | ...``."""
        def counter(service: str, name: str) -> int:
            return int(summary.stats.get(service, {}).get("counters", {}).get(name, 0))

        parts = []
        if self.now_ns is not None and self.start_ns is not None:
            total = f" / {(self.end_ns - self.start_ns) / 1e9:.1f}" if self.end_ns else ""
            parts.append(f"{(self.now_ns - self.start_ns) / 1e9:.1f}{total} s")
        go = sum(d.go for d in self.decisions)
        kinds = summary.outcome_kinds()
        p50 = self.latency_ms(50)
        frames = max(self.frames, int(summary.player_status.get("frames", 0)))
        parts += [f"frames {frames}",
                  f"observed {counter('perception', 'observed')}",
                  f"predictions {counter('predictor', 'predictions')}",
                  f"plans {counter('planner', 'plans')}",
                  f"go {go} / no-go {len(self.decisions) - go}",
                  f"grasps {kinds.get('success', 0)} of {len(summary.outcomes)}",
                  f"latency p50 {p50:.0f} ms" if p50 is not None else "latency p50 -"]
        return " | ".join(parts)

    def table(self, summary: RunSummary, restarts: dict[str, int], out: Path) -> str:
        """Each attempt (its outcome, and the prediction error when it was approved against
        ε) and the run's totals, then where to look next."""
        rows = [f"{'attempt':>7s}  {'outcome':34s} {'error at approval':>20s}  plan"]
        approvals = {d.plan_id: d for d in self.decisions if d.go and not d.update}
        for o in summary.outcomes:
            d = approvals.get(o["plan_id"])
            error = (f"{d.error_mm:.1f} mm (ε {d.threshold_mm:.0f})" if d is not None
                     and d.error_mm is not None else "-")
            outcome = ("success" if o["success"] else
                       f"aborted: {str(o.get('evidence', {}).get('reason', ''))[:25]}"
                       if o.get("aborted") else f"failed: {o.get('failure')}")
            rows.append(f"{o['attempt']:>7d}  {outcome:34s} {error:>20s}  {o['plan_id'] or '-'}")
        if not summary.outcomes:
            rows.append(f"{'':>7s}  no attempt")
        p50, p99 = self.latency_ms(50), self.latency_ms(99)
        go = [d for d in self.decisions if d.go]
        latency = (f"latency p50 / p99 {p50:.0f} / {p99:.0f} ms" if p50 is not None
                   and p99 is not None else "no decision")
        rows.append(f"gate: {len(go) - sum(d.update for d in go)} plans and "
                    f"{sum(d.update for d in go)} updates approved, "
                    f"{len(self.decisions) - len(go)} refused; {latency} (camera frame to "
                    f"decision); bad messages {summary.bad_total()}; restarts "
                    + (", ".join(f"{n} {k}" for n, k in restarts.items()) or "none"))
        rerun = f"rerun {out / 'run.rrd'}  |  " if (out / "run.rrd").exists() else ""
        rows.append(f"see it: {rerun}Foxglove: open {out / 'run.mcap'}"
                    f"  |  per hop: wavegrasp latency {out / 'run.mcap'}")
        return "\n".join(rows)

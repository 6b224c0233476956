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

    def gate(self) -> dict:
        """The gate's figures for ``summary.json``: plans and updates approved, refused, the
        camera-to-decision latency p50 / p99 (ms, None without a decision) and each approved
        plan's prediction error (mm)."""
        go = [d for d in self.decisions if d.go]
        updates = sum(d.update for d in go)
        errors = [round(d.error_mm, 2) for d in go if not d.update and d.error_mm is not None]
        p50, p99 = self.latency_ms(50), self.latency_ms(99)
        return {"plans_approved": len(go) - updates, "updates_approved": updates,
                "refused": len(self.decisions) - len(go),
                "latency_p50_ms": None if p50 is None else round(p50, 1),
                "latency_p99_ms": None if p99 is None else round(p99, 1),
                "error_at_approval_mm": errors}

    def table(self, summary: RunSummary, restarts: dict[str, int], out: Path) -> str:
        """Each attempt (its outcome, and the prediction error when it was approved against
        ε) and the run's totals, then where to look next."""
        rows = [f"{'attempt':>7s}  {'outcome':34s} {'error at approval':>20s}  plan"]
        approvals = {d.plan_id: d for d in self.decisions if d.go and not d.update}
        for o in summary.outcomes:
            d = approvals.get(o["plan_id"])
            error = (f"{d.error_mm:.1f} mm (ε {d.threshold_mm:.0f})" if d is not None
                     and d.error_mm is not None else "-")
            rows.append(f"{o['attempt']:>7d}  {outcome_text(o):34s} {error:>20s}  "
                        f"{o['plan_id'] or '-'}")
        if not summary.outcomes:
            rows.append(f"{'':>7s}  no attempt")
        rows.append(gate_line(self.gate(), summary.bad_total(), restarts))
        rows.append(see_it(out))
        return "\n".join(rows)


def outcome_text(outcome: dict) -> str:
    """An attempt's outcome (a GraspOutcome's fields) in a few words."""
    if outcome["success"]:
        return "success"
    if outcome.get("aborted"):
        return f"aborted: {str(outcome.get('evidence', {}).get('reason', ''))[:25]}"
    return f"failed: {outcome.get('failure')}"


def gate_line(gate: dict, bad: int, restarts: dict[str, int]) -> str:
    """The gate's figures (:meth:`Progress.gate`), bad messages and restarts in one line."""
    p50, p99 = gate["latency_p50_ms"], gate["latency_p99_ms"]
    latency = (f"latency p50 / p99 {p50:.0f} / {p99:.0f} ms" if p50 is not None
               and p99 is not None else "no decision")
    return (f"gate: {gate['plans_approved']} plans and {gate['updates_approved']} updates "
            f"approved, {gate['refused']} refused; {latency} (camera frame to decision); "
            f"bad messages {bad}; restarts "
            + (", ".join(f"{n} {k}" for n, k in restarts.items()) or "none"))


def see_it(out: Path) -> str:
    """The commands that open the run in ``out``: rerun (where run.rrd was written),
    Foxglove, and the latency per hop."""
    rerun = f"rerun {out / 'run.rrd'}  |  " if (out / "run.rrd").exists() else ""
    return (f"see it: {rerun}Foxglove: open {out / 'run.mcap'}"
            f"  |  per hop: wavegrasp latency {out / 'run.mcap'}")

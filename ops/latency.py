"""``wavegrasp latency RUN.mcap...``: where the milliseconds go, read from the messages' traces.

Every message the pipeline derives from a camera frame carries the frame's trace: the player's
publish time (from the CDR attachment: in a replay it stands for the capture), then each
service's receive and send times. A gate decision's trace therefore holds the whole chain
player → perception → predictor → planner → gate. This prints, per hop and end to end, the
p50 / p95 / p99 / max in milliseconds; the camera frames perception never reported on
(sequence gaps); and the time from capture to approval against the frame interval and the
plan's lead time. ``--out DIR`` also writes ``latency.json`` and ``latency.png`` there.
Hop times are wall clock, so a run's figures are only as good as its pacing: profile a
``--pace realtime`` run. Several runs are taken together: one run of a 40 s recording makes
only a handful of gate decisions, so its p99 is its maximum.
"""

from __future__ import annotations

import argparse
import json
import sys
from collections import defaultdict
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from wavegrasp.recording_io.own_messages import decode_own, own_topics
from wavegrasp.recording_io.reader import RecordingError, TruncatedRecording, read_mcap
from wavegrasp.runtime.trace import hop_times_ms
from wavegrasp.schemas import Hop

CHAIN_KEY = "wavegrasp/gate/decision"
OBSERVATION_KEY = "wavegrasp/perception/object"
PREDICTION_KEY = "wavegrasp/predictor/prediction"
PLAN_KEY = "wavegrasp/planner/plan"
#: The camera's frames as the run recorded them: its own, or across a tether the edge's.
POINTS_TOPICS = ("/trisect/points", "/wavegrasp/edge/points")
TOPICS = (*POINTS_TOPICS, *own_topics([CHAIN_KEY, OBSERVATION_KEY, PREDICTION_KEY, PLAN_KEY]))
NS_PER_MS = 1e6


@dataclass
class Latency:
    """What a run's traces say. ``hops`` and ``end_to_end`` hold milliseconds per decision."""

    path: Path | str  # the run.mcap, or the runs merged
    hops: dict[str, list[float]] = field(default_factory=lambda: defaultdict(list))
    end_to_end: list[float] = field(default_factory=list)
    #: Camera frame to perception's observation and to the predictor's prediction, ms, for
    #: every frame that got one (not only the few that end in a gate decision).
    to_observation: list[float] = field(default_factory=list)
    to_prediction: list[float] = field(default_factory=list)
    decision_times_s: list[float] = field(default_factory=list)  # recording s, per decision
    frames_published: int = 0
    frames_observed: int = 0
    frames_dropped: int = 0
    frame_interval_ms: float = float("nan")
    approvals_ms: list[float] = field(default_factory=list)  # capture -> go
    approval_leads_ms: list[float] = field(default_factory=list)  # capture -> grasp time
    warnings: list[str] = field(default_factory=list)  # e.g. a run file cut short

    def table(self) -> list[dict[str, float | str | int]]:
        rows = [_row(name, values) for name, values in self.hops.items()]
        rows.append(_row("camera frame -> observation", self.to_observation))
        rows.append(_row("camera frame -> prediction", self.to_prediction))
        rows.append(_row("camera frame -> gate decision", self.end_to_end))
        return rows

    def as_json(self) -> dict:
        return {"path": str(self.path), "table": self.table(),
                "frames_published": self.frames_published,
                "frames_observed": self.frames_observed, "frames_dropped": self.frames_dropped,
                "frame_interval_ms": self.frame_interval_ms,
                "approvals": len(self.approvals_ms),
                "capture_to_approval_ms": _row("", self.approvals_ms),
                "plan_lead_ms": _row("", self.approval_leads_ms), "warnings": self.warnings}


def _row(name: str, values: list[float]) -> dict[str, float | str | int]:
    v = np.asarray(values, dtype=float)
    if not len(v):
        return {"hop": name, "n": 0}
    p50, p95, p99 = np.percentile(v, [50, 95, 99])
    return {"hop": name, "n": len(v), "p50": float(p50), "p95": float(p95), "p99": float(p99),
            "max": float(v.max())}


def read_latency(path: Path) -> Latency:
    """Read ``path`` (a ``run.mcap``). Raises ValueError if it is no MCAP, is corrupt or has no
    traces. A file cut short (a recorder that was killed) is read up to its last complete chunk,
    with a warning in ``warnings``."""
    lat = Latency(Path(path))
    observed: set[int] = set()
    point_seqs: set[int] = set()
    point_stamps: list[tuple[int, int]] = []  # (sequence, log time ns) of each cloud
    plans: dict[str, dict] = {}
    topic, cut = "", ""
    try:
        for schema, channel, message in read_mcap(path, TOPICS):
            topic = channel.topic.lstrip("/")
            if channel.topic in POINTS_TOPICS:
                point_seqs.add(message.sequence)
                point_stamps.append((message.sequence, message.log_time))
            elif (own := decode_own(schema, channel, message)) is not None:
                msg = own.model_dump()
                if topic == OBSERVATION_KEY:
                    observed.add(msg["header"]["seq"])
                    _add_since_capture(lat.to_observation, msg)
                elif topic == PREDICTION_KEY:
                    _add_since_capture(lat.to_prediction, msg)
                elif topic == PLAN_KEY:
                    plans[msg["plan_id"]] = msg
                else:
                    _add_decision(lat, msg, plans.get(msg["plan_id"]))
    except TruncatedRecording as exc:
        lat.warnings.append(f"{exc}; the figures are of those")
        cut = str(exc).removeprefix(f"{path}: ")
    except RecordingError as exc:
        raise ValueError(str(exc)) from None
    except ValueError as exc:
        raise ValueError(f"{path}: {exc}") from None
    except (KeyError, TypeError) as exc:
        raise ValueError(f"{path}: a malformed {topic} message: {type(exc).__name__}: "
                         f"{exc}") from None
    if not lat.end_to_end:
        raise ValueError(f"{path}: no {CHAIN_KEY} messages with a trace"
                         + (f" ({cut})" if cut else ""))
    lat.frames_observed = len(observed)
    # The camera's sequence numbers run on from frame to frame: those between the first and
    # the last that perception never reported were dropped (the recorder may have written
    # only one cloud in N of a big camera's).
    seqs = point_seqs | observed
    if seqs:
        lat.frames_published = max(seqs) - min(seqs) + 1
        lat.frames_dropped = lat.frames_published - len(observed)
    if len(point_stamps) > 1:
        seq, stamp = np.diff(np.array(sorted(point_stamps), dtype=float), axis=0).T
        if (seq > 0).any():  # per frame, though only one cloud in N may be written
            lat.frame_interval_ms = float(np.median(stamp[seq > 0] / seq[seq > 0])) / NS_PER_MS
    return lat


def merge(runs: list[Latency]) -> Latency:
    """Several runs' figures as one (repeated replays of a recording: a p99 needs more gate
    decisions than one run makes)."""
    if len(runs) == 1:
        return runs[0]
    out = Latency(f"{len(runs)} runs ({', '.join(str(r.path) for r in runs)})")
    for r in runs:
        for name, values in r.hops.items():
            out.hops[name].extend(values)
        for name in ("end_to_end", "to_observation", "to_prediction", "decision_times_s",
                     "approvals_ms", "approval_leads_ms"):
            getattr(out, name).extend(getattr(r, name))
        out.frames_published += r.frames_published
        out.frames_observed += r.frames_observed
        out.frames_dropped += r.frames_dropped
        out.warnings.extend(r.warnings)
    intervals = [r.frame_interval_ms for r in runs if np.isfinite(r.frame_interval_ms)]
    out.frame_interval_ms = float(np.median(intervals)) if intervals else float("nan")
    return out


def _add_since_capture(values: list[float], msg: dict) -> None:
    """Append the milliseconds from the camera frame's publish (the trace's source) to
    ``msg``'s send; nothing for a message whose trace has no source (a camera that sends no
    publish time)."""
    trace = msg["header"]["trace"]
    if trace and trace[0]["service"] == "source":
        values.append((trace[-1]["sent_ns"] - trace[0]["sent_ns"]) / NS_PER_MS)


def _add_decision(lat: Latency, msg: dict, plan: dict | None) -> None:
    trace = [Hop(**h) for h in msg["header"]["trace"]]
    if not trace or trace[0].service != "source":
        raise ValueError(f"decision {msg['plan_id']}: trace does not start at the source")
    for name, ms in hop_times_ms(trace):
        lat.hops[name].append(ms)
    total = (trace[-1].sent_ns - trace[0].sent_ns) / NS_PER_MS
    lat.end_to_end.append(total)
    lat.decision_times_s.append(msg["header"]["stamp_ns"] * 1e-9)
    if msg["go"] and plan is not None:
        lat.approvals_ms.append(total)
        lat.approval_leads_ms.append((plan["t_grasp_ns"] - plan["header"]["stamp_ns"])
                                     / NS_PER_MS)


def format_table(lat: Latency) -> str:
    lines = [f"{lat.path}: {len(lat.end_to_end)} gate decisions",
             f"{'hop':32s} {'n':>6s} {'p50':>8s} {'p95':>8s} {'p99':>8s} {'max':>8s}  (ms)"]
    for row in lat.table():
        if row["n"]:
            lines.append(f"{row['hop']:32s} {row['n']:6d} {row['p50']:8.2f} {row['p95']:8.2f} "
                         f"{row['p99']:8.2f} {row['max']:8.2f}")
    lines.append(f"frames: {lat.frames_published} published, {lat.frames_observed} reported "
                 f"by perception, {lat.frames_dropped} dropped")
    if lat.approvals_ms:
        a, lead = np.median(lat.approvals_ms), np.median(lat.approval_leads_ms)
        lines.append(f"capture -> approval: {a:.1f} ms median over {len(lat.approvals_ms)} "
                     f"approvals, {a / lat.frame_interval_ms:.0%} of the "
                     f"{lat.frame_interval_ms:.0f} ms frame interval and "
                     f"{a / lead:.2%} of the plans' {lead / 1e3:.2f} s lead (median)"
                     if np.isfinite(lat.frame_interval_ms) else
                     f"capture -> approval: {a:.1f} ms median, {a / lead:.2%} of the plans' "
                     f"{lead / 1e3:.2f} s lead (median)")
    return "\n".join(lines)


def plot(lat: Latency, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (left, right) = plt.subplots(1, 2, figsize=(12, 4.5))
    rows = [r for r in lat.table() if r["n"]]
    names = [r["hop"] for r in rows]
    y = np.arange(len(rows))
    left.barh(y - 0.2, [r["p50"] for r in rows], 0.4, label="p50")
    left.barh(y + 0.2, [r["p99"] for r in rows], 0.4, label="p99")
    left.set_yticks(y, names, fontsize=8)
    left.invert_yaxis()
    left.set_xlabel("ms")
    left.set_title("per hop")
    left.legend()
    t = np.asarray(lat.decision_times_s)
    right.plot(t - t.min(), lat.end_to_end, ".", ms=3)
    right.axhline(25.0, color="r", lw=1, label="25 ms budget")
    right.set_xlabel("recording time, s")
    right.set_ylabel("camera frame -> gate decision, ms")
    right.set_title("end to end, per decision")
    right.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="wavegrasp latency", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("runs", type=Path, nargs="+", metavar="RUN.mcap",
                   help="a run's run.mcap (from wavegrasp up); several are taken together")
    p.add_argument("--out", type=Path, help="write latency.json and latency.png here")
    a = p.parse_args(argv)
    try:
        lat = merge([read_latency(run) for run in a.runs])
    except ValueError as exc:  # one line, whatever a library put in its message
        print(f"wavegrasp latency: {' '.join(str(exc).split())}", file=sys.stderr)
        return 2
    for warning in lat.warnings:
        print(f"wavegrasp latency: warning: {warning}", file=sys.stderr)
    print(format_table(lat))
    if a.out:
        a.out.mkdir(parents=True, exist_ok=True)
        (a.out / "latency.json").write_text(json.dumps(lat.as_json(), indent=2) + "\n")
        plot(lat, a.out / "latency.png")
        print(f"wrote {a.out / 'latency.json'} and {a.out / 'latency.png'}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

"""``wavegrasp soak [RECORDING] --minutes M``: the pipeline for a long while, memory watched.

Runs ``wavegrasp up --pace realtime`` on RECORDING (default: the sample) played over and over
(the player's ``loops``: each loop's times follow on from the last, one stream) for at least
M minutes, ``--tether MBIT`` as ``wavegrasp up``'s; run.mcap only, unless ``--rrd``. Every
``--sample-s`` seconds it reads the
resident memory of each service (with the processes it started: perception's mesh worker).
At the end it compares each service's memory over the run's last tenth with that over its
second tenth (after the start's caches have filled): ``growth``, per cent. It counts the
camera frames at each step that carried them: played, through the edge stage (with a
tether), reported by perception, acknowledged by the recorder; a frame the link carried
and a later step lacks is lost. Writes ``OUT/soak.json`` and ``OUT/memory.csv`` beside the
run's files and prints a table. Exit code 0 when every service stayed within ``--flat``
per cent and no frame was lost, 1 otherwise, 2 for bad arguments.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import signal
import statistics
import sys
import threading
import time
from pathlib import Path

import psutil

from wavegrasp.ops import launcher as up
from wavegrasp.ops.sample import default_recording
from wavegrasp.recording_io.reader import RecordingError, open_for_replay

MB = 1 << 20


def rss_mb(pid: int) -> float | None:
    """Resident memory of ``pid`` and its descendants, MB; None if it is gone."""
    try:
        proc = psutil.Process(pid)
        procs = [proc, *proc.children(recursive=True)]
    except psutil.Error:
        return None
    total = 0
    for p in procs:
        try:
            total += p.memory_info().rss
        except psutil.Error:  # a child that ended meanwhile
            continue
    return total / MB


class MemoryWatch:
    """Samples every service's memory from its own thread until stopped."""

    def __init__(self, run: up.Run, period_s: float) -> None:
        self.run, self.period_s = run, period_s
        self.samples: list[tuple[float, dict[str, float]]] = []  # (s since start, MB)
        self.stop = threading.Event()

    def watch(self) -> None:
        t0 = time.monotonic()
        while not self.stop.wait(self.period_s):
            row = {name: mb for name, proc in list(self.run.launcher.procs.items())
                   if (mb := rss_mb(proc.pid)) is not None}
            self.samples.append((round(time.monotonic() - t0, 1), row))

    def growth(self) -> dict[str, dict[str, float]]:
        """Per service: median MB over the second tenth of the samples and the last tenth,
        and the growth between them, per cent."""
        n = len(self.samples)
        tenth = max(1, n // 10)
        early, late = self.samples[tenth:2 * tenth], self.samples[-tenth:]
        result = {}
        for name in sorted({k for _, row in self.samples for k in row}):
            a = [row[name] for _, row in early if name in row]
            b = [row[name] for _, row in late if name in row]
            if a and b:
                ma, mb = statistics.median(a), statistics.median(b)
                result[name] = {"early_mb": round(ma, 1), "late_mb": round(mb, 1),
                                "peak_mb": round(max(r.get(name, 0) for _, r in self.samples), 1),
                                "growth_pct": round(100 * (mb / ma - 1), 2)}
        return result

    def write_csv(self, path: Path) -> None:
        names = sorted({k for _, row in self.samples for k in row})
        lines = [",".join(["seconds", *names])]
        lines += [",".join([str(t), *(f"{row[n]:.1f}" if n in row else "" for n in names)])
                  for t, row in self.samples]
        path.write_text("\n".join(lines) + "\n")


def frame_counts(summary: dict) -> dict[str, int]:
    """Camera frames at each step, from the services' last counters."""
    services = summary.get("services", {})

    def counters(name: str) -> dict[str, int]:
        return services.get(name, {}).get("counters", {})

    perception = counters("perception")
    counts = {"played": int(summary.get("player", {}).get("frames", 0))}
    if "edge" in services:
        counts["through the edge"] = int(counters("edge").get("frames", 0))
    counts["reported by perception"] = int(perception.get("observed", 0) + sum(
        v for k, v in perception.items() if k.startswith("missing: ")))
    counts["acknowledged by the recorder"] = int(counters("recorder").get("frames", 0))
    return counts


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="wavegrasp soak", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("recording", nargs="?", type=Path, help="default: the sample")
    p.add_argument("--minutes", type=float, default=60.0, help="how long at least (default 60)")
    p.add_argument("--tether", type=float, metavar="MBIT", help="as wavegrasp up's")
    p.add_argument("--sample-s", type=float, default=10.0,
                   help="seconds between memory samples (default 10)")
    p.add_argument("--flat", type=float, default=10.0,
                   help="the most a service's memory may grow, per cent (default 10)")
    p.add_argument("--out", type=Path, help="run folder (default: runs/soak-<date-time>)")
    p.add_argument("--rrd", action="store_true",
                   help="write run.rrd too (off by default: rerun's recording stream keeps "
                   "memory for all it wrote, rerun-io/rerun#12623; the recorder closes it "
                   "after WAVEGRASP_RRD_MINUTES)")
    a = p.parse_args(argv)
    recording = a.recording or default_recording()
    try:
        opened = open_for_replay(recording)
        if not (opened.start_ns and opened.end_ns and opened.end_ns > opened.start_ns):
            raise ValueError(f"{recording}: its length is not known")
        if not a.minutes > 0 or not a.sample_s > 0:
            raise ValueError("--minutes and --sample-s must be > 0")
        loops = math.ceil(a.minutes * 60e9 / (opened.end_ns - opened.start_ns))
        out = a.out or Path("runs") / time.strftime("soak-%Y%m%d-%H%M%S")
        argv_up = [str(recording), "--pace", "realtime", "--out", str(out)]
        if a.tether is not None:
            argv_up += ["--tether", str(a.tether)]
        environ = {**os.environ, "WAVEGRASP_LOOPS": str(loops),
                   **({} if a.rrd else {"WAVEGRASP_RRD": "false"})}
        run = up.prepare(up.parse_args(argv_up), environ)
    except (ValueError, RecordingError) as exc:
        print(f"wavegrasp soak: {exc}", file=sys.stderr)
        return 2
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: run.launcher.interrupted.set())
    memory = MemoryWatch(run, a.sample_s)
    thread = threading.Thread(target=memory.watch, name="memory", daemon=True)
    thread.start()
    why = up.execute(run)
    memory.stop.set()
    thread.join(timeout=5.0)
    summary = up.summarize(run, why)
    growth, frames = memory.growth(), frame_counts(summary)
    memory.write_csv(run.out / "memory.csv")
    lost = max(frames.values()) - min(frames.values()) if frames else 0
    flat = all(g["growth_pct"] <= a.flat for g in growth.values())
    report = {"recording": str(recording), "loops": loops, "ended": why,
              "minutes": round(summary["duration_s"] / 60, 1), "tether": summary.get("tether"),
              "memory": growth, "frames": frames, "frames_lost": lost,
              "grasps": summary.get("outcomes", [])}
    (run.out / "soak.json").write_text(json.dumps(report, indent=2) + "\n")
    print(f"{'service':16s} {'early MB':>9s} {'late MB':>8s} {'peak MB':>8s} {'growth':>7s}")
    for name, g in growth.items():
        print(f"{name:16s} {g['early_mb']:9.1f} {g['late_mb']:8.1f} {g['peak_mb']:8.1f} "
              f"{g['growth_pct']:6.1f}%")
    print("frames: " + ", ".join(f"{k} {v}" for k, v in frames.items()) + f"; lost {lost}")
    ok = why == "finished" and flat and lost == 0
    return 0 if ok else 1


if __name__ == "__main__":
    raise SystemExit(main())

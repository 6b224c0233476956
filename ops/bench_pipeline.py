"""The pipeline at a camera's rate: ``python -m wavegrasp.ops.bench_pipeline``.

Makes the recordings (cached: the paper's wave 2 and half-full can, seed 0, as ``wavegrasp
eval`` does), then runs ``wavegrasp up REC --pace realtime`` on each ``--runs`` times, every
service a process of its own, as a user would. Profiles (``--profiles``):

- ``dense``: 10 Hz, the camera's 320 x 240 image as a dense cloud (valid points only, about
  30 000);
- ``organized``: 30 Hz, a 672 x 376 organized cloud with rgb (252 672 points, NaN where
  stereo found nothing, 32 bytes a point: 8 MB a frame), as a stereo camera driver publishes.

Prints, per profile and over all its runs, each hop's and the end-to-end milliseconds
(p50 / p99 / max, from the messages' traces: ``wavegrasp latency``), camera frame to
observation and to prediction for every frame, the frames published, observed and dropped,
and the CPU seconds of each service per run (their processes' own counts). ``--out DIR``
keeps the runs there (default: a temporary folder, removed after) and writes
``bench_pipeline.json``.
"""

from __future__ import annotations

import argparse
import json
import shutil
import subprocess
import sys
import tempfile
from collections import defaultdict
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from wavegrasp.ops.latency import Latency, format_table, merge, read_latency
from wavegrasp.ops.sample import cached_recording
from wavegrasp.wavetank.scenario import CameraSpec, paper_scenario


@dataclass(frozen=True)
class Profile:
    """A camera to benchmark: its rate (Hz), image (pixels) and cloud kind."""

    rate_hz: float
    width: int
    height: int
    cloud: str

    def recording(self, seconds: float, seed: int) -> Path:
        """The profile's recording of ``seconds``, generated on first use."""
        camera = CameraSpec(width=self.width, height=self.height, rate_hz=self.rate_hz,
                            cloud=self.cloud)  # type: ignore[arg-type]
        name = f"bench-{self.cloud}-{self.rate_hz:g}hz-{self.width}x{self.height}"
        return cached_recording(paper_scenario(2, "can_half", name=name, seconds=seconds,
                                               seed=seed, camera=camera))


PROFILES = {"dense": Profile(10.0, 320, 240, "dense"),
            "organized": Profile(30.0, 672, 376, "organized")}


def run_once(recording: Path, out: Path) -> tuple[Latency, dict[str, float]]:
    """One realtime ``wavegrasp up`` of ``recording`` into ``out``: its latency and each
    service's CPU seconds."""
    proc = subprocess.run([sys.executable, "-m", "wavegrasp", "up", str(recording),
                           "--pace", "realtime", "--out", str(out)],
                          capture_output=True, text=True)
    (out / "up.log").write_text(proc.stdout + proc.stderr)
    if proc.returncode != 0:
        raise RuntimeError(f"wavegrasp up {recording} exited {proc.returncode}: see "
                           f"{out / 'up.log'}")
    summary = json.loads((out / "summary.json").read_text())
    cpu = {name: float(s.get("cpu_s", 0.0)) for name, s in summary["services"].items()}
    return read_latency(out / "run.mcap"), cpu


def cpu_table(runs: list[dict[str, float]]) -> str:
    """Each service's CPU seconds per run: median and max over ``runs``."""
    per: dict[str, list[float]] = defaultdict(list)
    for run in runs:
        for name, seconds in run.items():
            per[name].append(seconds)
    lines = [f"{'service':12s} {'CPU s/run':>10s} {'max':>8s}"]
    for name, values in sorted(per.items(), key=lambda kv: -np.median(kv[1])):
        lines.append(f"{name:12s} {np.median(values):10.2f} {max(values):8.2f}")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m wavegrasp.ops.bench_pipeline",
                                description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--profiles", default="dense,organized", help=", ".join(PROFILES))
    p.add_argument("--runs", type=int, default=5, help="runs per profile (default 5)")
    p.add_argument("--seconds", type=float, default=40.0,
                   help="recording seconds, after the player's lead-in (default 40)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", type=Path, help="keep the runs here (default: removed after)")
    a = p.parse_args(argv)
    names = a.profiles.split(",")
    if unknown := [n for n in names if n not in PROFILES]:
        p.error(f"unknown profile {', '.join(unknown)}: {', '.join(PROFILES)}")
    out = a.out or Path(tempfile.mkdtemp(prefix="bench_pipeline-"))
    report = {}
    try:
        for name in names:
            recording = PROFILES[name].recording(a.seconds, a.seed)
            results = [run_once(recording, out / f"{name}-{i}") for i in range(a.runs)]
            lat = merge([lat for lat, _ in results])
            lat.path = f"{name}: {a.runs} realtime runs of {recording.name}"
            print(format_table(lat))
            print(cpu_table([cpu for _, cpu in results]))
            print()
            report[name] = {**lat.as_json(), "cpu_s": [cpu for _, cpu in results]}
        if a.out:
            (out / "bench_pipeline.json").write_text(json.dumps(report, indent=2) + "\n")
    finally:
        if not a.out:
            shutil.rmtree(out, ignore_errors=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

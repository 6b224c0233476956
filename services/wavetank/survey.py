"""Generate every wave × object configuration and print the table in recordings/README.md.

``python -m wavegrasp.wavetank.survey [--seconds 30] [--seed 0] [--out DIR]``
"""

from __future__ import annotations

import argparse
import tempfile
from pathlib import Path

from wavegrasp.wavetank.analysis import dominant_period, motion_summary, read_groundtruth
from wavegrasp.wavetank.body import OBJECTS
from wavegrasp.wavetank.record import RecordConfig, generate
from wavegrasp.wavetank.waves import TABLE_I


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__)
    p.add_argument("--seconds", type=float, default=30.0)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--irregular", action="store_true")
    p.add_argument("--out", type=Path, help="keep the recordings here (default: discard)")
    a = p.parse_args(argv)
    with tempfile.TemporaryDirectory() as tmp:
        out = a.out or Path(tmp)
        out.mkdir(parents=True, exist_ok=True)
        print("| wave | object | period (s) / Tp | amp x, y, z (mm) | max speed (m/s) "
              "| points/frame | generation (× real time) | tether slack |")
        print("|---|---|---|---|---|---|---|---|")
        for wave, cond in TABLE_I.items():
            for name in OBJECTS:
                path = out / f"wave{wave}-{name}-seed{a.seed}.mcap"
                cfg = RecordConfig(wave=wave, object=name, seconds=a.seconds, seed=a.seed,
                                   irregular=a.irregular)
                facts = generate(cfg, path)
                t, pos = read_groundtruth(path)
                m = motion_summary(t, pos)
                print(f"| {wave} | {name} | {dominant_period(t, pos):.3f} / {cond.period_s} "
                      f"| {m['amp_x'] * 1e3:.0f}, {m['amp_y'] * 1e3:.0f}, {m['amp_z'] * 1e3:.0f} "
                      f"| {m['max_speed']:.2f} | {facts['points_per_frame']:.0f} "
                      f"| {a.seconds / facts['generation_s']:.1f} "
                      f"| {facts['slack_fraction']:.0%} |", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

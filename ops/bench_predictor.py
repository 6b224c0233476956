"""Predictor accuracy and speed: ``python -m wavegrasp.ops.bench_predictor [--seconds 40]``.

Generates wave-tank recordings of all 12 wave x object configurations, regular and JONSWAP
(into the cache, on first use), runs the perception pipeline over each to get the centroids the
predictor service would receive, then runs every model over them and prints, per recording and
model: RMSE of the predicted position 0.25, 0.5 and 1 wave period ahead (after 10 s of
warm-up), how often the 1-period error is within 2 sigma, and the update time (median, p99).

``--periods 0.8,1.2,...`` instead runs regular seas of those periods (0.15 m high) with each
object in the paper's tank: the periods a user's sea may have, beyond Table I's 1.08-1.25 s.
"""

from __future__ import annotations

import argparse

import numpy as np

from wavegrasp.ops.sample import cached_recording
from wavegrasp.perception.evaluate import run_perception
from wavegrasp.predictor import MODELS
from wavegrasp.predictor.evaluate import score
from wavegrasp.wavetank.body import OBJECTS
from wavegrasp.wavetank.waves import TABLE_I


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--seconds", type=float, default=40.0)
    p.add_argument("--seed", type=int, default=2)
    p.add_argument("--models", default=",".join(MODELS))
    p.add_argument("--seas", default="regular,jonswap")
    p.add_argument("--periods", help="comma-separated regular wave periods, seconds")
    a = p.parse_args(argv)
    models = a.models.split(",")
    if a.periods:
        return by_period([float(x) for x in a.periods.split(",")], models, a.seconds, a.seed)
    for sea in a.seas.split(","):
        print(f"\n{sea} seas: RMSE at 0.25T / 0.5T / 1T (mm), share of 1T errors within 2 sigma\n")
        print("| wave | object | " + " | ".join(models) + " |")
        print("|---|---|" + "---|" * len(models))
        totals = {m: [] for m in models}
        times = {m: [] for m in models}
        for wave, cond in TABLE_I.items():
            for obj in OBJECTS:
                path = cached_recording(wave=wave, object=obj, seconds=a.seconds, seed=a.seed,
                                        irregular=sea == "jonswap")
                track = run_perception(path)
                cells = []
                for m in models:
                    s = score(track, m, cond.period_s)
                    totals[m].append(s.rmse[-1])
                    times[m].append(s.update_ms)
                    cells.append(" / ".join(f"{e * 1e3:.1f}" for e in s.rmse)
                                 + f", {s.coverage:.0%}")
                print(f"| {wave} | {obj} | " + " | ".join(cells) + " |", flush=True)
        print()
        for m in models:
            t = np.concatenate(times[m])
            print(f"{m}: RMSE at 1T over configurations: mean {np.mean(totals[m]) * 1e3:.2f} mm,"
                  f" worst {np.max(totals[m]) * 1e3:.2f} mm; update {np.median(t):.3f} ms "
                  f"median, {np.percentile(t, 99):.3f} ms p99")
    return 0


def by_period(periods: list[float], models: list[str], seconds: float, seed: int) -> int:
    from wavegrasp.wavetank.scenario import SeaSpec, paper_scenario

    print("\nregular seas, 0.15 m: RMSE at 0.25T / 0.5T / 1T (mm), share of 1T errors within "
          "2 sigma\n")
    print("| period (s) | object | " + " | ".join(models) + " |")
    print("|---|---|" + "---|" * len(models))
    worst = {m: (0.0, 1.0) for m in models}
    for period in periods:
        for obj in OBJECTS:
            scenario = paper_scenario(2, obj, name=f"period{period:g}-{obj}", seconds=seconds,
                                      seed=seed, sea=SeaSpec(height_m=0.15, period_s=period))
            track = run_perception(cached_recording(scenario))
            cells = []
            for m in models:
                s = score(track, m, period)
                worst[m] = (max(worst[m][0], s.rmse[-1]), min(worst[m][1], s.coverage))
                cells.append(" / ".join(f"{e * 1e3:.1f}" for e in s.rmse)
                             + f", {s.coverage:.0%}")
            print(f"| {period:g} | {obj} | " + " | ".join(cells) + " |", flush=True)
    print()
    for m in models:
        print(f"{m}: worst RMSE at 1T {worst[m][0] * 1e3:.2f} mm, worst 2-sigma coverage "
              f"{worst[m][1]:.0%}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

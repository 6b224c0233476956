"""Planner success, speed and accuracy: ``python -m wavegrasp.ops.bench_planner``.

For all 12 wave x object configurations (40 s recordings, cached), perception's centroids feed
the default predictor; after 10 s of warm-up the planner plans on every warm prediction from
the arm's standby pose. Prints the share of predictions that got a reachable, timed,
collision-free plan, the planning time (median, p90) and how far the planned grasp position
is from where the object truly is at the grasp time (median).
"""

from __future__ import annotations

import argparse

import numpy as np

from wavegrasp.ops.sample import cached_recording
from wavegrasp.perception.evaluate import run_perception
from wavegrasp.planner.evaluate import score
from wavegrasp.recording_io.reader import open_recording
from wavegrasp.recording_io.ros_msgs import StaticTransforms, decode_tf
from wavegrasp.wavetank.body import OBJECTS
from wavegrasp.wavetank.waves import TABLE_I


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--seconds", type=float, default=40.0)
    p.add_argument("--seed", type=int, default=2)
    a = p.parse_args(argv)
    print("| wave | object | planned | planning median (ms) | p90 (ms) | grasp error median (mm) |")
    print("|---|---|---|---|---|---|")
    all_times, all_errors, planned, attempts = [], [], 0, 0
    for wave in TABLE_I:
        for name, spec in OBJECTS.items():
            path = cached_recording(wave=wave, object=name, seconds=a.seconds, seed=a.seed)
            tf = StaticTransforms()
            tf.update(decode_tf(next(m for m in open_recording(path).messages()
                                     if m.topic == "/tf_static").cdr))
            axis = None if spec.shape == "sphere" else np.array([0.0, 0.0, 1.0])
            s = score(run_perception(path), tf.lookup("world", "bravo_base_link"),
                      (spec.radius, spec.length / 2, axis))
            all_times.append(s.times_ms)
            all_errors.append(s.grasp_errors)
            planned, attempts = planned + s.plans, attempts + s.attempts
            print(f"| {wave} | {name} | {s.plans / max(s.attempts, 1):.1%} "
                  f"| {np.median(s.times_ms):.1f} | {np.percentile(s.times_ms, 90):.1f} "
                  f"| {np.median(s.grasp_errors) * 1e3:.1f} |", flush=True)
    t, e = np.concatenate(all_times), np.concatenate(all_errors)
    print(f"\nall: {planned / attempts:.1%} of {attempts} predictions planned; planning "
          f"{np.median(t):.1f} ms median, {np.percentile(t, 90):.1f} ms p90; grasp error "
          f"{np.median(e) * 1e3:.1f} mm median")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

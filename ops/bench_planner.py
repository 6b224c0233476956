"""Planner success, speed and accuracy: ``python -m wavegrasp.ops.bench_planner``.

For all 12 wave x object configurations (40 s recordings, cached), perception's centroids feed
the default predictor; after 10 s of warm-up the planner plans on every warm prediction from
the arm's standby pose. Prints the share of predictions that got a reachable, timed,
collision-free plan, the planning time (median, p90) and how far the planned grasp position
is from where the object truly is at the grasp time (median).

``--suite SEED --scenarios N`` does the same on the random suite's first N scenarios drawn
with SEED (30 s recordings, or ``--only I,J`` of them at ``--seconds``; those the arm
cannot grasp at all are listed, not scored), with
the most frequent rejections of each. The planner is given the object as perception last
reported it, and each plan's grasp is tried first on the next prediction, as in a run.
``--each-standby`` also scores each scenario from every one of its standby poses (the
planner service waits in the first and tries the others when nothing plans for a period).
"""

from __future__ import annotations

import argparse

import numpy as np

from wavegrasp.ops.sample import cached_recording
from wavegrasp.perception.evaluate import Track, run_perception
from wavegrasp.perception.main import observation
from wavegrasp.planner.collision import Body
from wavegrasp.planner.evaluate import score, warmup_sway
from wavegrasp.recording_io.reader import open_recording
from wavegrasp.recording_io.ros_msgs import StaticTransforms, decode_tf
from wavegrasp.schemas import Header
from wavegrasp.wavetank.body import OBJECTS
from wavegrasp.wavetank.waves import TABLE_I


def planner_body(track: Track) -> Body:
    """The object as the planner service sees it: perception's last fit, as observed."""
    if track.last_fit is None:
        return Body(0.05)
    return Body.from_observation(observation(Header(), track.last_fit,
                                             int(track.last_fit.inliers.sum()),
                                             track.last_span))


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--seconds", type=float, default=40.0)
    p.add_argument("--seed", type=int, default=2)
    p.add_argument("--suite", type=int, metavar="SEED",
                   help="score the random suite's scenarios drawn with SEED instead")
    p.add_argument("--scenarios", type=int, default=8)
    p.add_argument("--only", metavar="I,J", help="with --suite: only these scenarios (their "
                   "numbers, as in random-SEED-NNN), drawn with --seconds")
    p.add_argument("--each-standby", action="store_true", help="with --suite: also score "
                   "each scenario from every standby pose")
    a = p.parse_args(argv)
    if a.suite is not None:
        only = None if a.only is None else [int(i) for i in a.only.split(",")]
        return suite(a.suite, a.scenarios, only, a.seconds if only else 30.0,
                     a.each_standby)
    print("| wave | object | planned | planning median (ms) | p90 (ms) | grasp error median (mm) |")
    print("|---|---|---|---|---|---|")
    all_times, all_errors, planned, attempts = [], [], 0, 0
    for wave in TABLE_I:
        for name in OBJECTS:
            path = cached_recording(wave=wave, object=name, seconds=a.seconds, seed=a.seed)
            tf = StaticTransforms()
            tf.update(decode_tf(next(m for m in open_recording(path).messages()
                                     if m.topic == "/tf_static").cdr))
            track = run_perception(path)
            s = score(track, tf.lookup("world", "bravo_base_link"), planner_body(track))
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


def suite(seed: int, count: int, only: list[int] | None = None, seconds: float = 30.0,
          each_standby: bool = False) -> int:
    from scipy.spatial.transform import Rotation

    from wavegrasp.arm import ArmModel
    from wavegrasp.planner.standby import standby_poses
    from wavegrasp.wavetank.record import arm_mount
    from wavegrasp.wavetank.suite import draw_scenarios, grasp_verdict

    print("| scenario | object | shoulder to object (m) | planned | planning median (ms) "
          "| p90 (ms) | most rejected |")
    print("|---|---|---|---|---|---|---|")
    rates = []
    for s in draw_scenarios(count, seed, seconds=seconds)[0]:
        if only is not None and int(s.name.rsplit("-", 1)[1]) not in only:
            continue
        verdict = grasp_verdict(s)
        if verdict:
            print(f"| {s.name} | {s.object.family} | | not scored: {verdict} | | | |")
            continue
        position, quat = arm_mount(s)
        T = np.eye(4)
        T[:3, :3], T[:3, 3] = Rotation.from_quat(quat).as_matrix(), position
        o = s.object
        track = run_perception(cached_recording(s))
        body = planner_body(track)
        r = score(track, T, body)
        if not r.attempts:  # perception's centroids never warmed the predictor
            print(f"| {s.name} | {o.family} | | no warm prediction | | | |", flush=True)
            rates.append(0.0)
            continue
        rates.append(r.plans / r.attempts)
        top = ", ".join(f"{k} {n}" for k, n in r.rejected.most_common(2))
        print(f"| {s.name} | {o.family} {o.diameter_m * 100:.1f} cm "
              f"| {np.linalg.norm(s.shoulder() - s.rest):.2f} | {rates[-1]:.1%} "
              f"| {np.median(r.times_ms):.1f} | {np.percentile(r.times_ms, 90):.1f} "
              f"| {top} |", flush=True)
        if each_standby:
            for j, q in enumerate(standby_poses(ArmModel.load(), T, warmup_sway(track), body)):
                r = score(track, T, body, q_standby=q)
                print(f"| {s.name}, standby pose {j} | {np.round(q, 2).tolist()} | "
                      f"| {r.plans / max(r.attempts, 1):.1%} | | | |", flush=True)
    if rates:
        print(f"\n{len(rates)} scenarios scored: planned {np.mean(rates):.1%} on average, "
              f"worst {min(rates):.1%}; {sum(x >= 0.95 for x in rates)} at 95 % or more")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

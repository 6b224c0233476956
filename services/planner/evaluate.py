"""The planner against ground truth: offline over a recording, or from a run's messages."""

from __future__ import annotations

import time
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from wavegrasp.arm import ArmModel
from wavegrasp.perception.evaluate import Track
from wavegrasp.planner.approach import PredictedPath
from wavegrasp.planner.collision import Body
from wavegrasp.planner.plan import Hint, Plan, PlannerConfig, plan_grasp
from wavegrasp.planner.standby import standby_pose
from wavegrasp.predictor.models import make_predictor
from wavegrasp.recording_io.mcap_read import read_mcap
from wavegrasp.recording_io.own_messages import decode_own, own_topics
from wavegrasp.recording_io.ros_msgs import decode_pose
from wavegrasp.schemas import GateDecision, GraspPlan


@dataclass
class PlannerScore:
    """Warm predictions and plans made; planning times (ms); |P_f − truth at t_grasp| (m) of
    the plans whose grasp time the recording still covers; why candidates were rejected,
    over the predictions that got no plan."""

    attempts: int
    plans: int
    times_ms: np.ndarray
    grasp_errors: np.ndarray
    rejected: Counter = field(default_factory=Counter)


def warmup_sway(track: Track, warmup_s: float = 10.0) -> np.ndarray:
    """Where perception saw the object's centroid in the last 100 frames of the warm-up:
    shape (k, 3), metres, world (NaN where it did not)."""
    return track.centres[(track.stamps_ns - track.stamps_ns[0]) * 1e-9 < warmup_s][-100:]


def score(track: Track, T_world_base: np.ndarray, body: Body, warmup_s: float = 10.0,
          cfg: PlannerConfig | None = None, q_standby: np.ndarray | None = None
          ) -> PlannerScore:
    """Feed perception's centroids to the default predictor and plan on every warm forecast
    after ``warmup_s``, from the arm's standby pose facing where the object was seen during
    the warm-up (:func:`~wavegrasp.planner.standby.standby_pose`, where the arm waits between
    attempts; or from ``q_standby``, radians), each plan's grasp tried first on the next
    prediction as the service does. ``body``: the object as perception reports it."""
    cfg = cfg or PlannerConfig()
    arm, predictor = ArmModel.load(), make_predictor("blend")
    t_truth = (track.truth_ns - track.stamps_ns[0]) * 1e-9
    times, errors, attempts, plans, rejected = [], [], 0, 0, Counter()
    hint = None
    if q_standby is None:
        q_standby = standby_pose(arm, T_world_base, warmup_sway(track, warmup_s), body)
    for stamp, centre, sigma in zip(track.stamps_ns, track.centres, track.sigmas, strict=True):
        if np.isnan(centre[0]):
            continue
        t = (stamp - track.stamps_ns[0]) * 1e-9
        f = predictor.update(t, centre, sigma)
        if f is None or not f.warm or t < warmup_s:
            continue
        attempts += 1
        path = PredictedPath(f.t0 + f.leads, f.positions, np.nan_to_num(f.sigma, nan=1.0),
                             f.period_s)
        start = time.perf_counter()
        plan = plan_grasp(path, t, arm, T_world_base, q_standby, body, cfg, hint)
        times.append((time.perf_counter() - start) * 1e3)
        if isinstance(plan, Plan):  # as the service does
            hint = Hint.of(plan, path)
        plans += isinstance(plan, Plan)
        if not isinstance(plan, Plan):
            rejected.update(plan)
        if isinstance(plan, Plan) and plan.t_grasp <= t_truth[-1]:
            truth = np.array([np.interp(plan.t_grasp, t_truth, track.truth[:, i])
                              for i in range(3)])
            errors.append(np.linalg.norm(plan.grasp_T_world[:3, 3] - truth))
    return PlannerScore(attempts, plans, np.array(times), np.array(errors), rejected)


def approved_grasp_errors(run_mcap: Path) -> np.ndarray:
    """|grasp position − true centroid at t_grasp| (m) for every plan the gate approved."""
    plans, approved, truth = {}, set(), {}
    for schema, channel, msg in read_mcap(run_mcap, [
            *own_topics(["wavegrasp/planner/plan", "wavegrasp/gate/decision"]),
            "/groundtruth/object"]):
        if channel.topic == "/groundtruth/object":
            T, _, stamp = decode_pose(msg.data)
            truth[stamp] = T[:3, 3]
        elif isinstance(own := decode_own(schema, channel, msg), GraspPlan):
            plans[own.plan_id] = (own.t_grasp_ns, np.array([own.grasp.position.x,
                                                            own.grasp.position.y,
                                                            own.grasp.position.z]))
        elif isinstance(own, GateDecision) and own.go:
            approved.add(own.plan_id)
    stamps = np.array(sorted(truth))
    positions = np.array([truth[s] for s in stamps])
    errors = []
    for plan_id in approved & set(plans):
        t_grasp, position = plans[plan_id]
        if stamps[0] <= t_grasp <= stamps[-1]:
            true = [np.interp(t_grasp, stamps, positions[:, i]) for i in range(3)]
            errors.append(np.linalg.norm(position - true))
    return np.array(errors)

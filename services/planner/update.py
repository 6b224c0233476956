"""Closed-loop execution: an approved plan moved to where the newest prediction puts the
object at the grasp time, spliced from the arm's state.

The approach keeps its shape, its timing and the tool's orientation: its waypoints move by
the grasp point's shift and are solved again (each from the moved grasp's joint values, so
the arm stays on its branch). From ``update_delay_s`` after the prediction (the time to be
approved and reach the arm) ruckig takes the arm from the state the current trajectory gives
it then (position, velocity, acceleration), inside the arm's limits: before the approach,
to the moved P_init by the time the approach begins; during it (or where the approach begins
too soon for that), onto the moved approach ``splice_s`` (or a few times that) into it, the
way ros2_control's
joint_trajectory_controller splices a new trajectory into the one it runs. The grasp time
stays.

Times are seconds on the recording clock; positions metres, ``world``; joints radians.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
from scipy.interpolate import CubicSpline

from wavegrasp.arm import ArmModel
from wavegrasp.planner.approach import PredictedPath
from wavegrasp.planner.collision import Body, collides, first_contact
from wavegrasp.planner.plan import Plan, PlannerConfig, approach_joints
from wavegrasp.planner.timing import Limits, sample_segment, segment


def resample(times: np.ndarray, values: np.ndarray, t: np.ndarray | float) -> np.ndarray:
    """``values`` (k, n) sampled at ``times`` (k,) s, linearly at ``t`` (m,) s: (m, n); at a
    single ``t``: (n,)."""
    out = np.column_stack([np.interp(t, times, values[:, j]) for j in range(values.shape[1])])
    return out[0] if np.ndim(t) == 0 else out


def state_at(times: np.ndarray, q: np.ndarray, qd: np.ndarray, t: float
             ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Position, velocity and acceleration, each shape (n,), of the sampled trajectory
    ``times`` (k,) s, ``q`` and ``qd`` (k, n) at ``t`` s (acceleration from the velocities)."""
    acc = np.gradient(qd, times, axis=0) if len(times) > 1 else np.zeros_like(qd)
    return resample(times, q, t), resample(times, qd, t), resample(times, acc, t)


def update_plan(plan: Plan, path: PredictedPath, now: float, arm: ArmModel,
                T_world_base: np.ndarray, body: Body, cfg: PlannerConfig) -> Plan | str:
    """``plan`` (approved, executing) moved to ``path``'s position at its grasp time, from
    ``now`` + ``update_delay_s`` on; or why not: "unchanged" (moved less than
    ``update_min_m``), "moved too far", "too late" (the grasp is nearer than a splice),
    "unreachable", "cannot splice" (not within the arm's limits in ``splice_s``),
    "collision" (the moved trajectory meets the object on ``path`` where the one it replaces
    keeps clear). Where both meet it, the moved plan's ``t_contact`` says when the arm would
    first touch the object."""
    if not len(plan.knots):
        raise ValueError("plan has no approach knots: not one plan_grasp made")
    t_take = now + cfg.update_delay_s
    if t_take > plan.t_grasp - 2 * cfg.sample_dt_s:
        return "too late"
    p_f = plan.grasp_T_world[:3, 3]
    shift = path.at(plan.t_grasp) - p_f
    if np.linalg.norm(shift) < cfg.update_min_m:
        return "unchanged"
    if np.linalg.norm(shift) > cfg.update_max_m:
        return "moved too far"
    T_grasp = plan.grasp_T_world.copy()
    T_grasp[:3, 3] = p_f + shift
    T_base_world = np.linalg.inv(T_world_base)
    q_f = arm.inverse(T_base_world @ T_grasp, plan.qs[-1], max_iter=cfg.ik_max_iter,
                      restarts=-1)
    if q_f is None or np.abs(q_f - plan.qs[-1]).max() > cfg.max_joint_step_rad:
        return "unreachable"
    points = plan.points + shift
    qs = approach_joints(arm, T_base_world @ T_grasp, T_base_world, points, q_f, cfg, {})
    if qs is None:
        return "unreachable"
    spline = CubicSpline(plan.knots, qs, bc_type="clamped")
    limits = Limits(arm.max_velocity, arm.max_acceleration, arm.max_jerk)
    dt = cfg.sample_dt_s
    pieces = _to_p_init(plan, qs[0], t_take, limits, dt) if t_take < plan.knots[0] else None
    if pieces is not None:
        t_app = plan.times[plan.times >= plan.knots[0]]
        # A move that ends as the approach starts (it waits until it must go) ends on the
        # approach's first sample: kept twice, the times did not increase and the schema
        # refused the update (4 updates in 2 of the 144 experiment runs).
        to_p_init = pieces[0] < t_app[0] - dt * 1e-3
        times = np.concatenate([pieces[0][to_p_init], t_app])
        q = np.vstack([pieces[1][to_p_init], spline(t_app)])
        qd = np.vstack([pieces[2][to_p_init], spline(t_app, 1)])
    else:  # in the approach, or too near its start to be at rest at P_init first
        joined = _join(plan, spline, t_take, limits, cfg.splice_s, dt)
        if joined is None:
            return "cannot splice"
        times, q, qd = joined
    if np.any(np.abs(qd) > arm.max_velocity * 1.001):
        return "cannot splice"
    keep = plan.times < times[0] - dt / 2
    # Refused only where the trajectory it replaces keeps clear: an irregular sea's forecast
    # reshapes the swing, not just moves it: in a run of the JONSWAP tank (wave 2, buoy),
    # of 239 updates refused for a collision, 179 had the old trajectory meeting the object
    # as newly predicted too; kept, the arm went on where the object would not be.
    # Where both meet it, the update goes with when the arm would touch the object: the
    # gate aborts an attempt heading into it (the arm backs out) rather than let it hit.
    t_contact = None
    if collides(arm, T_world_base, times, q, path, body, cfg.clearance_m, plan.t_final):
        if not collides(arm, T_world_base, plan.times[~keep], plan.q[~keep], path, body,
                        cfg.clearance_m, plan.t_final):
            return "collision"
        t_contact = first_contact(arm, T_world_base, times, q, path, body, plan.t_final)
    return replace(plan, t_contact=t_contact, times=np.concatenate([plan.times[keep], times]),
                   q=np.vstack([plan.q[keep], q]), qd=np.vstack([plan.qd[keep], qd]),
                   tool=(T_world_base @ arm.forward_batch(np.vstack([plan.q[keep], q])))
                   [:, :3, 3], points=points, grasp_T_world=T_grasp, qs=qs)


def _to_p_init(plan: Plan, q_init: np.ndarray, t_take: float, limits: Limits, dt: float
               ) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """Before the approach: the move to the moved P_init ``q_init`` (n,), time-optimal
    (ruckig) from the arm's state, at rest there by the approach's start; an arm still
    waiting starts when it was to, or as much sooner as the longer move needs. Times (k,),
    positions and velocities (k, n) from the move's start, or None if it cannot be there
    in time."""
    start = max(t_take, plan.move_s[0])
    zero = np.zeros(len(q_init))
    move = segment(*state_at(plan.times, plan.q, plan.qd, start), q_init, zero, limits)
    if move is not None and start + move.duration > plan.knots[0] and start > t_take:
        start = max(t_take, plan.knots[0] - move.duration)  # the arm rests until it moves
        move = segment(*state_at(plan.times, plan.q, plan.qd, start), q_init, zero, limits)
    if move is None or start + move.duration > plan.knots[0] + 1e-6:
        return None
    t, q, qd = sample_segment(move, start, dt)
    hold = np.arange(t[-1] + dt, plan.knots[0] - dt / 2, dt)
    return (np.concatenate([t, hold]), np.vstack([q, np.tile(q_init, (len(hold), 1))]),
            np.vstack([qd, np.zeros((len(hold), len(q_init)))]))


def _join(plan: Plan, spline: CubicSpline, t_take: float, limits: Limits, splice_s: float,
          dt: float) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """A ruckig move from the arm's state at ``t_take`` onto the moved approach ``spline``
    ``splice_s`` into it (else two or three times that, at most by the grasp time), then the
    spline. Times (k,), positions and velocities (k, n), or None if not within the arm's
    limits."""
    state = state_at(plan.times, plan.q, plan.qd, t_take)
    for k in (1, 2, 3):
        t_join = min(max(t_take, plan.knots[0]) + k * splice_s, plan.t_grasp)
        join = t_join - t_take
        move = segment(*state, spline(t_join), spline(t_join, 1), limits, min_duration=join,
                       a1=spline(t_join, 2))
        if move is not None and move.duration <= join + 1e-3:
            break
        if t_join >= plan.t_grasp:
            return None
    else:
        return None
    t_after = np.concatenate([[t_join], plan.times[plan.times > t_join + dt / 2]])
    local = np.arange(0.0, join - dt / 2, dt)
    states = [move.trajectory.at_time(float(x)) for x in local]
    n = len(plan.qs[0])
    return (np.concatenate([t_take + local, t_after]),
            np.vstack([np.array([s[0] for s in states]).reshape(len(local), n),
                       spline(t_after)]),
            np.vstack([np.array([s[1] for s in states]).reshape(len(local), n),
                       spline(t_after, 1)]))

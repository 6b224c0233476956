"""Plan one grasp: pick the time, generate candidates, reject the unreachable, the colliding
and the untimeable, and return the first that passes (candidates are ordered best first).

Times are seconds on the recording clock; positions metres. The arm's joint values are in its
own model (radians); ``T_world_base`` places its mount ``bravo_base_link`` in ``world``.
"""

from __future__ import annotations

from collections import Counter
from dataclasses import dataclass, field

import numpy as np
from pydantic import BaseModel, Field

from wavegrasp.arm import ArmModel
from wavegrasp.planner.approach import (
    PredictedPath,
    grasp_times,
    motion_direction,
    offset_directions,
    waypoints,
)
from wavegrasp.planner.timing import Limits, sample_path, sample_segment, segment, spline_path


class PlannerConfig(BaseModel):
    grasp_time: str = Field("slowest", description="'slowest' or 'period' (the paper's Δt = T)")
    min_lead_s: float = Field(0.6, description="no grasp sooner than this after planning")
    start_delay_s: float = Field(0.25, description="time for the plan to be approved and sent")
    alpha_m: float = 0.12
    waypoint_count: int = 3
    beta_m: float = 0.02
    final_m: float = 0.05
    clearance_m: float = Field(0.015, description="arm to object, before the final move")
    cruise_mps: float = Field(0.4, description="tool speed assumed for the earliest grasp")
    approach_s: float = Field(0.8, description="time assumed for P_init to P_f")
    sample_dt_s: float = 0.02
    max_times: int = 3
    max_offsets: int = 3
    ik_max_iter: int = 40
    ik_restarts: int = 2


@dataclass
class Plan:
    """A timed grasp. times : (k,) s; q, qd : (k, 6); tool : (k, 3) metres, world;
    points : the Cartesian waypoints (m, 3), world, P_init first and P_f last."""

    t_start: float
    t_grasp: float
    times: np.ndarray
    q: np.ndarray
    qd: np.ndarray
    tool: np.ndarray
    points: np.ndarray
    grasp_T_world: np.ndarray
    approach: np.ndarray
    confidence: float
    rejected: Counter = field(default_factory=Counter)


def grasp_pose(p: np.ndarray, n: np.ndarray, d: np.ndarray) -> np.ndarray:
    """Tool pose (4, 4) at ``p``: pointing at the object from the offset side (z = −n), the
    open slot between the jaws (y) along the object's motion ``d``, so the object, arriving
    along d against the jaws' final move, enters between them; the jaws close along x."""
    z = -n / np.linalg.norm(n)
    y = d - (d @ z) * z
    y /= np.linalg.norm(y)
    T = np.eye(4)
    T[:3, :3] = np.column_stack([np.cross(y, z), y, z])
    T[:3, 3] = p
    return T


def segment_points_distance(p0: np.ndarray, p1: np.ndarray, c: np.ndarray) -> float:
    """Smallest distance from the segment p0-p1 to the points ``c`` (k, 3)."""
    d = p1 - p0
    s = np.clip((c - p0) @ d / max(d @ d, 1e-12), 0.0, 1.0)
    return float(np.min(np.linalg.norm(p0 + s[:, None] * d - c, axis=1)))


def collides(arm: ArmModel, T_world_base: np.ndarray, times: np.ndarray, q: np.ndarray,
             path: PredictedPath, body: tuple[float, float, np.ndarray | None],
             clearance: float, final_from: float) -> bool:
    """Does any link come within ``clearance`` of the object along its predicted path?

    ``body`` = (radius, half length, axis): a sphere, or a capsule along the axis (points on
    its axis stand for it). Before ``final_from`` every link counts; during the final move
    the jaws and the wrist (the last three capsules) may close in: that is the grasp.
    """
    radius, half, axis = body
    spine = np.linspace(-1.0, 1.0, 5)[:, None] * max(half - radius, 0.0) * (
        axis if axis is not None else np.zeros(3))
    R, t = T_world_base[:3, :3], T_world_base[:3, 3]
    for ti, qi in zip(times[::2], q[::2], strict=True):
        centre = path.at(min(ti, path.times_s[-1])) + spine
        capsules = arm.link_capsules(qi)
        if ti >= final_from:
            capsules = capsules[:-3]
        for p0, p1, r in capsules:
            if segment_points_distance(R @ p0 + t, R @ p1 + t, centre) < radius + r + clearance:
                return True
    return False


def plan_grasp(path: PredictedPath, now: float, arm: ArmModel, T_world_base: np.ndarray,
               q_now: np.ndarray, body: tuple[float, float, np.ndarray | None],
               cfg: PlannerConfig) -> Plan | Counter:
    """The best feasible plan, or a Counter of why every candidate was rejected.

    body : (radius, half length, unit axis or None) of the object, metres, world.
    """
    limits = Limits(arm.max_velocity, arm.max_acceleration, arm.max_jerk)
    T_base_world = np.linalg.inv(T_world_base)
    base_world = T_world_base[:3, 3]
    rejected: Counter = Counter()
    if np.linalg.norm(path.positions - base_world, axis=1).min() > arm.reach_m + 0.2:
        rejected["unreachable"] += 1
        return rejected
    # No grasp sooner than the arm could get there: from its tool to P_init at a modest
    # Cartesian speed, then the approach itself.
    tool_world = (T_world_base @ arm.forward(q_now))[:3, 3]
    reach_time = np.linalg.norm(path.positions - tool_world, axis=1).min() / cfg.cruise_mps
    earliest = now + cfg.start_delay_s + max(cfg.min_lead_s, reach_time + cfg.approach_s)
    for t_g in grasp_times(path, earliest, cfg.grasp_time)[:cfg.max_times]:
        p_f = path.at(t_g)
        d = motion_direction(path, t_g)
        # Offsets towards the arm and from above first: the arm does not reach around the object.
        towards = 0.5 * (base_world - p_f) / np.linalg.norm(base_world - p_f) + [0.0, 0.0, 1.0]
        for n in offset_directions(d, towards)[:cfg.max_offsets]:
            points = waypoints(p_f, n, d, cfg.alpha_m, cfg.waypoint_count, cfg.beta_m,
                               cfg.final_m)
            T_grasp = grasp_pose(p_f, n, d)
            q_f = arm.inverse(T_base_world @ T_grasp, q_now, max_iter=cfg.ik_max_iter,
                              restarts=cfg.ik_restarts)
            if q_f is None:
                rejected["unreachable"] += 1
                continue
            roll = q_f[-1] + np.array([0.0, np.pi, -np.pi])  # the same grasp, jaws swapped
            ok = (roll >= arm.lower[-1]) & (roll <= arm.upper[-1])
            best = roll[ok][np.argmin(np.abs(roll[ok] - q_now[-1]))]
            if best != q_f[-1]:
                T_grasp = T_grasp @ np.diag([-1.0, -1.0, 1.0, 1.0])
            q_f[-1] = best
            # Cheap test before the other waypoints: could the arm even be at P_f in time?
            direct = segment(q_now, np.zeros(6), np.zeros(6), q_f, np.zeros(6), limits)
            if direct is None or now + cfg.start_delay_s + direct.duration > t_g:
                rejected["cannot be timed"] += 1
                continue
            qs, seed = [], q_f
            for p in points[::-1]:  # from the grasp back to P_init, each seeding the next
                T = T_grasp.copy()
                T[:3, 3] = p
                q = arm.inverse(T_base_world @ T, seed, max_iter=cfg.ik_max_iter,
                                restarts=cfg.ik_restarts)
                if q is None:
                    break
                qs.append(q)
                seed = q
            if len(qs) < len(points):
                rejected["unreachable"] += 1
                continue
            qs = np.array(qs[::-1])
            approach = spline_path(qs, limits)
            pre = segment(q_now, np.zeros(6), np.zeros(6), qs[0], np.zeros(6), limits)
            if pre is None:
                rejected["cannot be timed"] += 1
                continue
            d_path = approach.duration
            t_start = now + cfg.start_delay_s
            hold = t_g - d_path - (t_start + pre.duration)
            if hold < 0:
                rejected["cannot be timed"] += 1
                continue
            t_pre, q_pre, v_pre = sample_segment(pre, t_start, cfg.sample_dt_s)
            t_app, q_app, v_app = sample_path(approach, t_g - d_path, cfg.sample_dt_s)
            t_hold = np.arange(t_pre[-1] + cfg.sample_dt_s, t_app[0], cfg.sample_dt_s)
            times = np.concatenate([t_pre, t_hold, t_app])
            q = np.vstack([q_pre, np.tile(qs[0], (len(t_hold), 1)), q_app])
            qd = np.vstack([v_pre, np.zeros((len(t_hold), 6)), v_app])
            final_from = t_g - d_path * (1 - approach.spline.x[-2])
            if collides(arm, T_world_base, times, q, path, body, cfg.clearance_m, final_from):
                rejected["collision"] += 1
                continue
            tool = np.array([(T_world_base @ arm.forward(qi))[:3, 3] for qi in q])
            sigma = float(np.interp(t_g, path.times_s, path.sigma))
            speed = float(np.linalg.norm(path.velocity(t_g)))
            confidence = float(np.exp(-sigma / 0.01) / (1.0 + speed))
            return Plan(t_start, t_g, times, q, qd, tool, points, T_grasp, -n, confidence,
                        rejected)
    if not rejected:
        rejected["no grasp time in the prediction"] += 1
    return rejected

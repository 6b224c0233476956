"""Time scaling in joint space.

The approach through the waypoints is a clamped cubic spline (scipy) in joint space, knots at
cumulative joint distance, stretched in time just enough that velocity, acceleration and jerk
stay within the arm's limits everywhere (they scale as 1/D, 1/D², 1/D³ with the duration D),
so it starts and ends at rest and passes every waypoint. The move from wherever the arm is to
the start of the approach is one ruckig segment to a single target; ruckig's intermediate
waypoints are never used (they call a cloud service).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from ruckig import InputParameter, Result, Ruckig, Trajectory
from scipy.interpolate import CubicSpline


@dataclass(frozen=True)
class Limits:
    """Per joint, shape (6,): rad/s, rad/s², rad/s³."""

    velocity: np.ndarray
    acceleration: np.ndarray
    jerk: np.ndarray


@dataclass
class Segment:
    trajectory: Trajectory
    duration: float


def segment(q0: np.ndarray, v0: np.ndarray, a0: np.ndarray, q1: np.ndarray, v1: np.ndarray,
            limits: Limits, min_duration: float = 0.0) -> Segment | None:
    """Time-optimal (or ``min_duration``) move from state 0 to (q1, v1, zero acceleration)."""
    n = len(q0)
    otg, inp, traj = Ruckig(n), InputParameter(n), Trajectory(n)
    inp.current_position, inp.current_velocity, inp.current_acceleration = q0, v0, a0
    inp.target_position, inp.target_velocity = q1, v1
    inp.target_acceleration = np.zeros(n)
    inp.max_velocity, inp.max_acceleration = limits.velocity, limits.acceleration
    inp.max_jerk = limits.jerk
    if min_duration > 0:
        inp.minimum_duration = min_duration
    try:
        result = otg.calculate(inp, traj)
    except RuntimeError:
        return None
    if result not in (Result.Working, Result.Finished):
        return None
    return Segment(traj, traj.duration)


@dataclass
class SplinePath:
    """q(t) for t in [0, duration]: positions (6,), radians."""

    spline: CubicSpline
    duration: float

    def at(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Positions and velocities at times ``t`` (k,) s from the path's start: (k, 6) each."""
        u = np.clip(t / self.duration, 0.0, 1.0)
        return self.spline(u), self.spline(u, 1) / self.duration


def spline_path(qs: np.ndarray, limits: Limits, margin: float = 0.9) -> SplinePath:
    """A clamped cubic spline through ``qs`` (k, 6), timed as short as velocity, acceleration
    and jerk within ``margin`` of the limits allow."""
    legs = np.linalg.norm(np.diff(qs, axis=0), axis=1)
    # Knots at the cumulative square root of the leg lengths ("centripetal"): no overshoot,
    # and no violent acceleration out of short legs next to the ends, where it is at rest.
    knots = np.concatenate([[0.0], np.cumsum(np.sqrt(np.maximum(legs, 1e-9)))])
    spline = CubicSpline(knots / knots[-1], qs, bc_type="clamped")
    u = np.linspace(0.0, 1.0, 200)
    need = [np.max(np.abs(spline(u, k)) / (margin * lim)) ** (1.0 / k)
            for k, lim in ((1, limits.velocity), (2, limits.acceleration), (3, limits.jerk))]
    return SplinePath(spline, max(max(need), 0.05))


def sample_segment(seg: Segment, start: float, dt: float) -> tuple[np.ndarray, np.ndarray,
                                                                  np.ndarray]:
    """Times (s, from ``start``), positions and velocities every ``dt``, end included."""
    local = np.append(np.arange(0.0, seg.duration, dt), seg.duration)
    states = [seg.trajectory.at_time(float(t)) for t in local]
    return (start + local, np.array([s[0] for s in states]).reshape(len(local), -1),
            np.array([s[1] for s in states]).reshape(len(local), -1))


def sample_path(path: SplinePath, start: float, dt: float) -> tuple[np.ndarray, np.ndarray,
                                                                    np.ndarray]:
    local = np.append(np.arange(0.0, path.duration, dt), path.duration)
    q, qd = path.at(local)
    return start + local, q, qd

"""Inverse kinematics: Levenberg-Marquardt damped least squares inside the joint limits.

The damping follows Sugihara (2011): lambda = E + 1e-4 with E half the squared weighted error,
large far from the target (robust) and small near it (fast). Each step is capped and then
clamped to the joint limits. An attempt that stalls is restarted from the next seed; the seeds
are fixed, so the result is deterministic.
"""

from __future__ import annotations

import math
from collections.abc import Iterable

import numpy as np

from wavegrasp.arm.kinematics import Chain
from wavegrasp.arm.transforms import rotation_vector

#: Weight of one radian of orientation error against one metre of position error (m/rad).
ROTATION_WEIGHT = 0.3
#: Largest change of any joint in one iteration (radians or metres).
MAX_STEP = 0.4
#: An attempt stops when its error has not fallen by 1 % in this many iterations.
PATIENCE = 12


def _perpendicular(a: np.ndarray) -> np.ndarray:
    """A unit vector perpendicular to the unit vector a, shape (3,)."""
    v = np.cross(a, [1.0, 0.0, 0.0] if abs(a[0]) < 0.9 else [0.0, 1.0, 0.0])
    return v / np.linalg.norm(v)


def _rotation_error(R: np.ndarray, R_target: np.ndarray | None,
                    approach: np.ndarray | None) -> np.ndarray:
    """Rotation vector (shape (3,), radians, frame base) from the tool's orientation R to the
    target: to R_target, or (approach given) turning the tool's z axis onto `approach`."""
    if R_target is not None:
        return rotation_vector(R_target @ R.T)
    z = R[:, 2]
    c = np.cross(z, approach)
    s = float(np.linalg.norm(c))
    angle = math.atan2(s, float(z @ approach))
    if s < 1e-12:
        return np.zeros(3) if angle < 1.0 else math.pi * _perpendicular(approach)
    return c * (angle / s)


def _attempt(chain: Chain, lower: np.ndarray, upper: np.ndarray, q: np.ndarray,
             p_target: np.ndarray, R_target: np.ndarray | None, approach: np.ndarray | None,
             position_tol: float, angle_tol: float, max_iter: int) -> np.ndarray | None:
    w = ROTATION_WEIGHT
    free = None if approach is None else np.eye(3) - np.outer(approach, approach)
    q = np.clip(q, lower, upper)
    eye = np.eye(len(q))
    best, since = math.inf, 0
    for _ in range(max_iter):
        T, P, Z = chain.frames(q)
        e_p = p_target - T[:3, 3]
        e_r = _rotation_error(T[:3, :3], R_target, approach)
        # math.sqrt of the dot product is what np.linalg.norm computes, without its overhead.
        if math.sqrt(e_p @ e_p) <= position_tol and math.sqrt(e_r @ e_r) <= angle_tol:
            return q
        J = chain.jacobian_at(T, P, Z)
        J[3:] *= w
        if free is not None:  # rotation about the approach axis is free
            J[3:] = free @ J[3:]
        e = np.concatenate([e_p, w * e_r])
        err = 0.5 * float(e @ e)
        if err < 0.99 * best:
            best, since = err, 0
        else:
            since += 1
            if since >= PATIENCE:
                return None
        dq = np.linalg.solve(J.T @ J + (err + 1e-4) * eye, J.T @ e)
        big = float(np.abs(dq).max())
        if big > MAX_STEP:
            dq *= MAX_STEP / big
        q = np.minimum(np.maximum(q + dq, lower), upper)
    return None


def solve(chain: Chain, lower: np.ndarray, upper: np.ndarray, seeds: Iterable[np.ndarray],
          p_target: np.ndarray, R_target: np.ndarray | None = None,
          approach: np.ndarray | None = None, position_tol: float = 1e-3,
          angle_tol: float = math.radians(2.0), max_iter: int = 100) -> np.ndarray | None:
    """Joint values, shape (n,), within [lower, upper] that put the tool at p_target (shape
    (3,), metres, frame base) with orientation R_target (shape (3, 3)) or with its z axis
    along the unit `approach` (shape (3,)); the first seed that converges wins; None if none
    does. max_iter counts iterations per seed."""
    if (R_target is None) == (approach is None):
        raise ValueError("give exactly one of R_target and approach")
    for seed in seeds:
        q = _attempt(chain, lower, upper, np.asarray(seed, dtype=float), p_target, R_target,
                     approach, position_tol, angle_tol, max_iter)
        if q is not None:
            return q
    return None


def flip_last_roll(chain: Chain, lower: np.ndarray, upper: np.ndarray, q: np.ndarray,
                   q_seed: np.ndarray) -> np.ndarray:
    """For a symmetric parallel jaw, turning the last joint by pi (if it rolls about the tool's
    z axis through the tool point) gives the same grasp: of q and its flips within limits,
    return the one whose last joint is closest to q_seed's."""
    T, P, Z = chain.frames(q)
    on_axis = np.linalg.norm(np.cross(Z[-1], T[:3, 3] - P[-1])) < 1e-9
    if chain.movable[-1].type == "prismatic" or not on_axis or abs(Z[-1] @ T[:3, 2]) < 1 - 1e-9:
        return q
    options = [q[-1] + k * math.pi for k in (-2, -1, 0, 1, 2)]
    options = [v for v in options if lower[-1] <= v <= upper[-1]]
    out = q.copy()
    out[-1] = min(options, key=lambda v: abs(v - q_seed[-1]))
    return out


def wrist_twins(lower: np.ndarray, upper: np.ndarray, q: np.ndarray) -> list[np.ndarray]:
    """q and the joint values that put the tool exactly where q does by turning the wrist
    over: the third-last and last joints turned by pi either way and the second-last
    negated (a roll-pitch-roll wrist whose axes meet). Only those within limits; none but q
    for an arm whose wrist does not turn over so (:func:`wrist_turns_over`)."""
    twins = (_turned_over(q, a, b) for a in (-math.pi, math.pi) for b in (-math.pi, math.pi))
    return [q] + [t for t in twins if np.all(t >= lower) and np.all(t <= upper)]


def wrist_turns_over(chain: Chain, lower: np.ndarray, upper: np.ndarray) -> bool:
    """Does turning the wrist over (:func:`wrist_twins`) keep the tool where it was? Checked
    by forward kinematics at two arbitrary poses: it holds everywhere or (but for a
    coincidence) nowhere."""
    if len(lower) < 3:
        return False
    for s in (0.3, 0.7):
        q = lower + s * (upper - lower)
        twin = _turned_over(q, math.pi, math.pi)
        if not np.allclose(chain.frames(q)[0], chain.frames(twin)[0], atol=1e-9):
            return False
    return True


def _turned_over(q: np.ndarray, a: float, b: float) -> np.ndarray:
    """q with the wrist turned over: the third-last joint turned by ``a``, the last by ``b``
    (radians), the second-last negated."""
    twin = q.copy()
    twin[-3] += a
    twin[-2] = -twin[-2]
    twin[-1] += b
    return twin

"""Does the arm, moving along a planned trajectory, touch the object on its predicted path?

The arm is its links' capsules (:meth:`~wavegrasp.arm.ArmModel.capsules_batch`); the object is
a sphere, or a capsule along its axis, following the predicted centroid. Positions metres,
``world``; times seconds on the recording clock.
"""

from __future__ import annotations

import numpy as np

from wavegrasp.arm import ArmModel
from wavegrasp.planner.approach import PredictedPath

#: (radius, half length, unit axis or None) of the object, metres, world.
Body = tuple[float, float, np.ndarray | None]


def extent(body: Body, direction: np.ndarray) -> float:
    """How far the object reaches from its centroid along the unit ``direction``, metres."""
    radius, half, axis = body
    return radius + (0.0 if axis is None else abs(float(axis @ direction)) * max(half - radius, 0))


def _spine(body: Body) -> np.ndarray:
    """Points (5, 3) along the object's axis, relative to its centroid, that with its radius
    make it a capsule (all zero for a sphere)."""
    radius, half, axis = body
    return np.linspace(-1.0, 1.0, 5)[:, None] * max(half - radius, 0.0) * (
        axis if axis is not None else np.zeros(3))


def hand_hits(arm: ArmModel, T_grasp: np.ndarray, body: Body) -> bool:
    """Would the hand (palm, not the fingers) touch the object with the tool at ``T_grasp``
    (4, 4, world) and the object's centroid at the tool point? No kinematics needed."""
    p0, p1, link_radius = arm.hand_capsules
    R, t = T_grasp[:3, :3], T_grasp[:3, 3]
    gap = segments_points_distance((p0 @ R.T + t)[None], (p1 @ R.T + t)[None],
                                   (t + _spine(body))[None])
    return bool(np.any(gap[0] < body[0] + link_radius))


def segments_points_distance(p0: np.ndarray, p1: np.ndarray, c: np.ndarray) -> np.ndarray:
    """Smallest distance from each segment p0-p1 (arrays, shape (m, k, 3)) to the points
    ``c`` (shape (m, s, 3)) of the same row: array, shape (m, k), metres."""
    d = p1 - p0
    rel = c[:, None, :, :] - p0[:, :, None, :]  # (m, k, s, 3)
    s = np.clip(np.einsum("mksi,mki->mks", rel, d)
                / np.maximum(np.einsum("mki,mki->mk", d, d), 1e-12)[..., None], 0.0, 1.0)
    return np.linalg.norm(rel - s[..., None] * d[:, :, None, :], axis=-1).min(axis=2)


def clearance(arm: ArmModel, T_world_base: np.ndarray, q: np.ndarray, centres: np.ndarray,
              body: Body) -> float:
    """The smallest gap, metres, between the arm at ``q`` (shape (n,), radians) and the
    object at any of ``centres`` (shape (k, 3) or (3,), metres, world); negative where they
    overlap."""
    p0, p1, link_radius = arm.capsules_batch(np.asarray(q)[None])
    R, t = T_world_base[:3, :3], T_world_base[:3, 3]
    points = (np.reshape(centres, (-1, 1, 3)) + _spine(body)).reshape(1, -1, 3)
    gap = segments_points_distance(p0 @ R.T + t, p1 @ R.T + t, points)
    return float(np.min(gap[0] - link_radius) - body[0])


def collides(arm: ArmModel, T_world_base: np.ndarray, times: np.ndarray, q: np.ndarray,
             path: PredictedPath, body: Body, clearance: float, final_from: float) -> bool:
    """Does any link come within ``clearance`` of the object at any of ``times`` (shape (k,))
    with the arm at ``q`` (shape (k, n), radians)?

    From ``final_from`` on (the final move: the grasp itself) the jaw fingers may close in
    and the rest of the arm may come near, but must not touch.
    """
    radius = body[0]
    centres = path.at(np.minimum(times, path.times_s[-1])).reshape(-1, 1, 3) + _spine(body)
    p0, p1, link_radius = arm.capsules_batch(q)
    R, t = T_world_base[:3, :3], T_world_base[:3, 3]
    gap = segments_points_distance(p0 @ R.T + t, p1 @ R.T + t, centres) - radius - link_radius
    final = times >= final_from
    need = np.where(final[:, None], 0.0, clearance) * np.ones_like(gap)
    if arm.jaw_capsule_count:
        need[final, -arm.jaw_capsule_count:] = -np.inf
    return bool(np.any(gap < need))

"""Does the arm, moving along a planned trajectory, touch the object on its predicted path?

The arm is its links' capsules (:meth:`~wavegrasp.arm.ArmModel.capsules_batch`); the object is
a :class:`Body` following the predicted centroid. Positions metres, ``world``; times seconds on
the recording clock.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from wavegrasp.arm import ArmModel
from wavegrasp.arm.transforms import cross
from wavegrasp.planner.approach import PredictedPath
from wavegrasp.schemas import ObjectObservation, Vec3


@dataclass(frozen=True)
class Body:
    """The object as the planner models it, metres, world: a sphere of ``radius`` (no
    ``axis``), or that sphere swept along the unit ``axis`` to ``half_length`` from the
    centroid either way (a cylinder: a capsule), and for a box also across its axis along
    ``breadth_axis`` (unit, ⟂ ``axis`` and ``side``) to ``half_breadth``: a box of thinnest
    extent ``2 * radius`` (along the unit ``side``) with its edges rounded.
    """

    radius: float
    half_length: float = 0.0
    axis: np.ndarray | None = None
    side: np.ndarray | None = None
    half_breadth: float = 0.0

    @classmethod
    def from_observation(cls, msg: ObjectObservation) -> Body:
        """The body perception reports (its radius, length and axis; a box's side and
        breadth), or a 5 cm sphere if it reports no size."""
        if msg.radius_m is None:
            return cls(0.05)
        def unit(v: Vec3 | None) -> np.ndarray | None:
            return None if v is None else np.array([v.x, v.y, v.z]) / max(
                float(np.linalg.norm([v.x, v.y, v.z])), 1e-12)
        axis, half = unit(msg.axis), (msg.length_m or 2 * msg.radius_m) / 2
        if axis is not None and msg.side is not None and msg.side_width_m and msg.breadth_m:
            return cls(msg.side_width_m / 2, half, axis, unit(msg.side), msg.breadth_m / 2)
        return cls(msg.radius_m, half, axis)

    @property
    def breadth_axis(self) -> np.ndarray | None:
        return None if self.side is None or self.axis is None else cross(self.axis, self.side)

    @property
    def faces(self) -> list[np.ndarray] | None:
        """A box's face normals across its axis, thinnest first: the jaws close along one;
        None for a sphere or cylinder."""
        b = self.breadth_axis
        return None if b is None else [self.side, b]

    @property
    def half_size(self) -> float:
        """Its farthest reach from the centroid along any of its axes."""
        return max(self.radius, self.half_length, self.half_breadth)

    def rotated(self, R: np.ndarray) -> Body:
        """The same body with its directions turned by ``R`` (3, 3)."""
        return replace(self, axis=None if self.axis is None else R @ self.axis,
                       side=None if self.side is None else R @ self.side)

    def extent(self, direction: np.ndarray) -> float:
        """How far it reaches from its centroid along the unit ``direction``, metres."""
        out = self.radius
        if self.axis is not None:
            out += abs(float(self.axis @ direction)) * max(self.half_length - self.radius, 0.0)
        b = self.breadth_axis
        if b is not None:
            out += abs(float(b @ direction)) * max(self.half_breadth - self.radius, 0.0)
        return out

    def spine(self) -> np.ndarray:
        """Points (k, 3) relative to its centroid that, each with ``radius``, cover it: one
        at the centroid for a sphere, five along the axis for a capsule, and rows of those
        at most ``radius`` apart across a box's breadth."""
        if self.axis is None:
            return np.zeros((1, 3))
        line = np.linspace(-1.0, 1.0, 5)[:, None] * max(self.half_length - self.radius, 0.0)
        points = line * self.axis
        b, spread = self.breadth_axis, max(self.half_breadth - self.radius, 0.0)
        if b is None or spread == 0.0:
            return points
        rows = int(np.ceil(2.0 * spread / self.radius)) + 1
        offsets = np.linspace(-spread, spread, rows)[:, None] * b
        return (points[None, :, :] + offsets[:, None, :]).reshape(-1, 3)


def hand_hits(arm: ArmModel, T_grasp: np.ndarray, body: Body) -> bool:
    """Would the hand (palm, not the fingers) touch the object with the tool at ``T_grasp``
    (4, 4, world) and the object's centroid at the tool point? No kinematics needed."""
    p0, p1, link_radius = arm.hand_capsules
    R, t = T_grasp[:3, :3], T_grasp[:3, 3]
    gap = segments_points_distance((p0 @ R.T + t)[None], (p1 @ R.T + t)[None],
                                   (t + body.spine())[None])
    return bool(np.any(gap[0] < body.radius + link_radius))


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
    points = (np.reshape(centres, (-1, 1, 3)) + body.spine()).reshape(1, -1, 3)
    gap = segments_points_distance(p0 @ R.T + t, p1 @ R.T + t, points)
    return float(np.min(gap[0] - link_radius) - body.radius)


def collides(arm: ArmModel, T_world_base: np.ndarray, times: np.ndarray, q: np.ndarray,
             path: PredictedPath, body: Body, clearance: float, final_from: float) -> bool:
    """Does any link come within ``clearance`` of the object at any of ``times`` (shape (k,))
    with the arm at ``q`` (shape (k, n), radians)?

    From ``final_from`` on (the final move: the grasp itself) the jaw fingers may close in
    and the rest of the arm may come near, but must not touch.
    """
    radius = body.radius
    centres = path.at(np.minimum(times, path.times_s[-1])).reshape(-1, 1, 3) + body.spine()
    p0, p1, link_radius = arm.capsules_batch(q)
    R, t = T_world_base[:3, :3], T_world_base[:3, 3]
    gap = segments_points_distance(p0 @ R.T + t, p1 @ R.T + t, centres) - radius - link_radius
    final = times >= final_from
    need = np.where(final[:, None], 0.0, clearance) * np.ones_like(gap)
    if arm.jaw_capsule_count:
        need[final, -arm.jaw_capsule_count:] = -np.inf
    return bool(np.any(gap < need))

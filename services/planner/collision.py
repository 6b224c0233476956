"""Does the arm, moving along a planned trajectory, touch the object on its predicted path?

The arm is its links' capsules (:meth:`~wavegrasp.arm.ArmModel.capsules_batch`); the object is
a :class:`Body` following the predicted centroid. Positions metres, ``world``; times seconds on
the recording clock.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from wavegrasp.arm import ArmModel
from wavegrasp.arm.transforms import cross, frame_along
from wavegrasp.planner.approach import PredictedPath
from wavegrasp.schemas import ObjectObservation, Vec3

#: metres: a box's distance is measured exactly below this; beyond it, a lower bound. More
#: than a link's radius and the clearance asked of it together (6 and 1 cm on our arm): a
#: link's capsule is nearer than the clearance only where its axis is nearer than that.
NEAR_M = 0.15

#: metres: the most apart the points sampled along a link's axis are where it is checked
#: against a box (the distance found is at most half this above the true one)
LINK_SAMPLE_M = 0.01


@dataclass(frozen=True)
class Turns:
    """How the object turns as it sways, from its recent observations: ``times`` (m,), s,
    increasing; ``rotations`` (m, 3, 3) from its latest orientation to the one observed
    then; the sea's ``period_s``. Its orientation at a time to come is the one observed
    whole periods before it: measured on a box rocking 15° either way, 0.2-0.7° off at the
    grasp, where its orientation when the plan was made was 13-15° off."""

    times: np.ndarray
    rotations: np.ndarray
    period_s: float

    def at(self, t: float | np.ndarray) -> np.ndarray:
        """Rotations, shape (k, 3, 3), from the latest orientation to that at each ``t``
        (shape (k,) or a scalar), seconds; none (the identity) before the record."""
        t = np.atleast_1d(np.asarray(t, dtype=float))
        periods = np.maximum(np.ceil((t - self.times[-1]) / self.period_s - 1e-9), 0.0)
        back = t - periods * self.period_s
        i = np.clip(np.searchsorted(self.times, back), 1, len(self.times) - 1)
        i = np.where(back - self.times[i - 1] < self.times[i] - back, i - 1, i)
        out = self.rotations[i]
        out[back < self.times[0]] = np.eye(3)
        return out


@dataclass(frozen=True)
class Body:
    """The object as the planner models it, metres, world: a sphere of ``radius`` (no
    ``axis``), or that sphere swept along the unit ``axis`` to ``half_length`` from the
    centroid either way (a cylinder: a capsule), or a box: ``half_length`` along its axis,
    ``half_breadth`` along ``breadth_axis`` (unit, ⟂ ``axis`` and ``side``) and ``radius``
    along the unit ``side``, its thinnest. ``turns``: how it turns as it sways. ``offset``:
    metres along ``axis`` from the centroid to the middle of its length (a bottle's neck
    moves its centroid towards the body: a capsule centred on the centroid left 3 cm of a
    23 cm bottle's neck outside). ``seabed``: the plane (a, b, c, d) perception found the
    seabed in, world, unit normal up (a x + b y + c z + d = 0), which the arm keeps off as
    it keeps off the object (None: not seen): an arm mounted 16 cm above it, moved as if it
    were not there, swept its forearm 9 cm into it and jammed (random-71-032).
    """

    radius: float
    half_length: float = 0.0
    axis: np.ndarray | None = None
    side: np.ndarray | None = None
    half_breadth: float = 0.0
    #: How it turns over time (None: it keeps its orientation).
    turns: Turns | None = None
    offset: float = 0.0
    seabed: np.ndarray | None = None

    @classmethod
    def from_observation(cls, msg: ObjectObservation) -> Body:
        """The body perception reports (its radius, length and axis; a box's side and
        breadth), or a 5 cm sphere if it reports no size."""
        seabed = seabed_plane(msg)
        if msg.radius_m is None:
            return cls(0.05, seabed=seabed)
        def unit(v: Vec3 | None) -> np.ndarray | None:
            return None if v is None else np.array([v.x, v.y, v.z]) / max(
                float(np.linalg.norm([v.x, v.y, v.z])), 1e-12)
        axis, half = unit(msg.axis), (msg.length_m or 2 * msg.radius_m) / 2
        if axis is not None and msg.side is not None and msg.side_width_m and msg.breadth_m:
            return cls(msg.side_width_m / 2, half, axis, unit(msg.side), msg.breadth_m / 2,
                       seabed=seabed)
        offset = (msg.axial_offset_m or 0.0) if axis is not None else 0.0
        return cls(msg.radius_m, half, axis, offset=offset, seabed=seabed)

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
        return max(self.radius, self.half_length + abs(self.offset), self.half_breadth)

    @property
    def frame(self) -> np.ndarray | None:
        """A box's orientation, shape (3, 3), columns: its side, breadth axis and axis; None
        for anything else."""
        if self.axis is None or self.side is None:
            return None
        return np.column_stack([self.side, cross(self.axis, self.side), self.axis])

    @property
    def orientation(self) -> np.ndarray | None:
        """How it is turned, shape (3, 3): a box's :attr:`frame`; for a body round about its
        axis, a frame whose third column is the axis (its turn about the axis changes
        nothing); None for a sphere."""
        if self.frame is not None or self.axis is None:
            return self.frame
        return frame_along(self.axis)

    def at(self, t: float) -> Body:
        """The body as it will be turned at ``t`` seconds (itself if it keeps still)."""
        if self.turns is None:
            return self
        return self.rotated(self.turns.at(t)[0])

    def gaps(self, p0: np.ndarray, p1: np.ndarray, centres: np.ndarray,
             times: np.ndarray | None = None) -> np.ndarray:
        """Distance, metres, from each segment p0-p1 (arrays, shape (k, c, 3), world) to
        the object's surface with its centroid at ``centres`` (shape (k, 3)) and, given
        ``times`` (shape (k,), s), a box turned as it will be then: array, shape (k, c),
        negative where a segment is inside. A box is its own faces and corners (exact below
        :data:`NEAR_M`, at least that beyond it); anything else the rounded model
        :meth:`spine` sweeps (turned, given ``times``, as it will be). With a ``seabed``,
        a segment's height above it where that is less."""
        out = self._object_gaps(p0, p1, centres, times)
        if self.seabed is None:
            return out
        n, d = self.seabed[:3], self.seabed[3]
        return np.minimum(out, np.minimum(p0 @ n, p1 @ n) + d)

    def _object_gaps(self, p0: np.ndarray, p1: np.ndarray, centres: np.ndarray,
                     times: np.ndarray | None) -> np.ndarray:
        if self.frame is None:
            spine = self.spine()[None]  # (1, m, 3), or turned as it will be at each time
            if self.turns is not None and times is not None and self.axis is not None:
                spine = np.einsum("kij,mj->kmi", self.turns.at(times), spine[0])
            return segments_points_distance(p0, p1, centres[:, None, :] + spine) - (
                self.radius)
        frames = np.broadcast_to(self.frame, (len(centres), 3, 3))  # the box's axes each time
        if self.turns is not None and times is not None:
            frames = self.turns.at(times) @ self.frame
        # The box itself only where a segment comes near the sphere round it; elsewhere
        # that sphere's gap, a lower bound of at least NEAR_M (most of a box's planning
        # time was here).
        half = np.array([self.radius, self.half_breadth, self.half_length])
        out = segments_points_distance(p0, p1, centres[:, None, :]) - float(np.linalg.norm(half))
        k, c = np.nonzero(out < NEAR_M)
        if not len(k):
            return out
        a, b = p0[k, c], p1[k, c]  # (n, 3)
        count = int(np.ceil(np.linalg.norm(b - a, axis=-1).max() / LINK_SAMPLE_M)) + 1
        u = np.linspace(0.0, 1.0, count)[:, None]
        samples = a[:, None, :] + u * (b - a)[:, None, :]  # (n, m, 3)
        local = np.einsum("nmi,nij->nmj", samples - centres[k, None, :], frames[k])
        over = np.abs(local) - half
        distance = np.linalg.norm(np.maximum(over, 0.0), axis=-1) + np.minimum(
            over.max(axis=-1), 0.0)
        out[k, c] = distance.min(axis=-1)
        return out

    def rotated(self, R: np.ndarray) -> Body:
        """The same body with its directions turned by ``R`` (3, 3), keeping that
        orientation (the seabed stays where it is)."""
        return replace(self, axis=None if self.axis is None else R @ self.axis,
                       side=None if self.side is None else R @ self.side, turns=None)

    def extent(self, direction: np.ndarray) -> float:
        """How far it reaches from its centroid along the unit ``direction``, metres: a
        box's corners (the rounded model was inside them: across a box 30° off its faces it
        was 5 cm narrower, and a jaw preshaped for it closed on the box's edges and pushed
        it out); a capsule round anything else (an ellipsoid's or a bottle's ends are
        rounded: 10° off its equator, the rims of a cylinder round a 13 x 15 cm ellipsoid
        reach 7.7 cm, wider than the jaw)."""
        if self.side is None:
            if self.axis is None:
                return self.radius
            along = float(self.axis @ direction)
            return self.radius + max(along * end for end in self.spine_ends())
        along = abs(float(self.axis @ direction))
        b = self.breadth_axis
        return (along * self.half_length + abs(float(b @ direction)) * self.half_breadth
                + abs(float(self.side @ direction)) * self.radius)

    def spine_ends(self) -> tuple[float, float]:
        """Where along its axis, metres from the centroid, the segment :meth:`spine` spans
        begins and ends: ``radius`` inside its ends (``offset`` ± ``half_length``), or, for
        a body no longer than it is wide, the one point nearest the centroid whose sphere
        takes in both ends (a flat ellipsoid's sphere is not moved by its offset)."""
        lo, hi = self.offset - self.half_length, self.offset + self.half_length
        if hi - lo >= 2.0 * self.radius:
            return lo + self.radius, hi - self.radius
        centre = min(max(0.0, hi - self.radius), lo + self.radius)
        return centre, centre

    def spine(self) -> np.ndarray:
        """Points (k, 3) relative to its centroid that, each with ``radius``, cover it: one
        at the centroid for a sphere, five along the axis for a cylinder (a capsule) between
        its :meth:`spine_ends`."""
        if self.axis is None:
            return np.zeros((1, 3))
        a, b = self.spine_ends()
        return np.linspace(a, b, 5)[:, None] * self.axis


def seabed_plane(msg: ObjectObservation, max_tilt_deg: float = 30.0) -> np.ndarray | None:
    """The seabed plane ``msg`` reports, (a, b, c, d), world, unit normal; None without one
    or where its normal is more than ``max_tilt_deg`` from straight up (a face of the object
    or a wall, not a floor the arm stands over)."""
    if msg.seabed_normal is None or msg.seabed_offset_m is None:
        return None
    n = np.array([msg.seabed_normal.x, msg.seabed_normal.y, msg.seabed_normal.z])
    n = n / max(float(np.linalg.norm(n)), 1e-12)
    if n[2] < np.cos(np.radians(max_tilt_deg)):
        return None
    return np.append(n, msg.seabed_offset_m)


def hand_hits(arm: ArmModel, T_grasp: np.ndarray, body: Body) -> bool:
    """Would the hand (palm, not the fingers) touch the object with the tool at ``T_grasp``
    (4, 4, world) and the object's centroid at the tool point? No kinematics needed."""
    p0, p1, link_radius = arm.hand_capsules
    R, t = T_grasp[:3, :3], T_grasp[:3, 3]
    gap = body.gaps((p0 @ R.T + t)[None], (p1 @ R.T + t)[None], t[None])
    return bool(np.any(gap[0] < link_radius))


def jaw_lead(arm: ArmModel, direction: np.ndarray) -> float:
    """How far the open jaw's fingers reach beyond the tool point along ``direction`` (unit,
    frame tool), metres, their thickness included."""
    p0, p1, radius = arm.jaw_capsules
    if not len(radius):
        return 0.0
    return float((np.maximum(p0 @ direction, p1 @ direction) + radius).max())


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
    """The smallest gap, metres, between the arm at ``q`` (shape (n,), or (k, n): each of
    k poses, radians) and the object at any of ``centres`` (shape (m, 3) or (3,), metres,
    world); negative where they overlap."""
    q = np.atleast_2d(q)
    p0, p1, link_radius = arm.capsules_batch(q)  # (k, links, 3)
    R, t = T_world_base[:3, :3], T_world_base[:3, 3]
    centres = np.reshape(centres, (-1, 3))
    m = len(centres)
    # Every pose against every centre: (k * m) rows.
    p0, p1 = (np.repeat(p @ R.T + t, m, axis=0) for p in (p0, p1))
    gap = body.gaps(p0, p1, np.tile(centres, (len(q), 1)))
    return float(np.min(gap - link_radius))


def collides(arm: ArmModel, T_world_base: np.ndarray, times: np.ndarray, q: np.ndarray,
             path: PredictedPath, body: Body, clearance: float, final_from: float,
             q_stay: np.ndarray | None = None) -> bool:
    """Does any link come within ``clearance`` of the object at any of ``times`` (shape (k,))
    with the arm at ``q`` (shape (k, n), radians)?

    From ``final_from`` on (the final move: the grasp itself) the jaw fingers may close in
    and the rest of the arm may come near, but must not touch. Given ``q_stay`` (shape
    (n,)), a link need come no nearer than the object would come to it over ``times`` with
    the arm staying there: an arm waiting where the object sways through may move out of
    its way.
    """
    gap = _gaps(arm, T_world_base, times, q, path, body)
    final = times >= final_from
    need = np.where(final[:, None], 0.0, clearance) * np.ones_like(gap)
    if arm.jaw_capsule_count:
        need[final, -arm.jaw_capsule_count:] = -np.inf
    if q_stay is not None:
        staying = _gaps(arm, T_world_base, times, np.tile(q_stay, (len(times), 1)), path, body)
        need = np.minimum(need, staying.min(axis=0))
    return bool(np.any(gap < need))


def first_contact(arm: ArmModel, T_world_base: np.ndarray, times: np.ndarray, q: np.ndarray,
                  path: PredictedPath, body: Body, final_from: float) -> float | None:
    """The first of ``times`` (k,) s at which a link of the arm at ``q`` (k, n) radians is
    surely inside the object on ``path``: deeper than twice the prediction's sigma there (a
    contact, not a near miss nor the forecast's noise); None if none is. In the final move
    (from ``final_from``) the fingers may meet it."""
    if not len(times):
        return None
    gap = _gaps(arm, T_world_base, times, q, path, body)
    if arm.jaw_capsule_count:
        gap[times >= final_from, -arm.jaw_capsule_count:] = np.inf
    depth = 2.0 * np.interp(times, path.times_s, path.sigma)
    hit = np.flatnonzero(np.any(gap < -depth[:, None], axis=1))
    return float(times[hit[0]]) if len(hit) else None


def _gaps(arm: ArmModel, T_world_base: np.ndarray, times: np.ndarray, q: np.ndarray,
          path: PredictedPath, body: Body) -> np.ndarray:
    """Each link's gap, metres, to the object on ``path`` at ``times`` (k,) with the arm at
    ``q`` (k, n): shape (k, links)."""
    centres = path.at(np.minimum(times, path.times_s[-1])).reshape(-1, 3)
    p0, p1, link_radius = arm.capsules_batch(q)
    R, t = T_world_base[:3, :3], T_world_base[:3, 3]
    return body.gaps(p0 @ R.T + t, p1 @ R.T + t, centres, times) - link_radius

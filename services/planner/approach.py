"""Where and when to grasp, and the Cartesian approach (the paper's section IV-F).

P_f is the predicted centroid at the grasp time; P_init = P_f + α n with n orthogonal to the
object's motion (equation 8); waypoints P_i = P_init + (i/N)(P_f − P_init) + β_i n (equation
9); the last move, into P_f, goes against the object's motion. Positions metres, ``world``.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np

from wavegrasp.arm.transforms import cross
from wavegrasp.schemas import MotionPrediction
from wavegrasp.schemas.path import path_at, path_spline


@dataclass(frozen=True)
class PredictedPath:
    """times_s : array, shape (m,), seconds on the recording clock; positions : (m, 3);
    sigma : (m,), metres; period_s : the motion's period."""

    times_s: np.ndarray
    positions: np.ndarray
    sigma: np.ndarray
    period_s: float

    @classmethod
    def from_message(cls, pred: MotionPrediction) -> PredictedPath:
        if len(pred.samples) < 3:
            raise ValueError(f"prediction has {len(pred.samples)} samples, need at least 3")
        s = pred.samples
        return cls(np.array([x.t_ns for x in s]) * 1e-9,
                   np.array([[x.x, x.y, x.z] for x in s]), np.array([x.sigma for x in s]),
                   pred.period_s)

    @cached_property
    def spline(self):  # noqa: ANN201 (scipy's CubicSpline)
        return path_spline(self.times_s, self.positions)

    def at(self, t: float | np.ndarray) -> np.ndarray:
        """Position(s) at ``t`` seconds (cubic between samples, see
        :mod:`wavegrasp.schemas.path`): shape (3,) for a scalar ``t``, else (k, 3)."""
        return path_at(self.spline, t)

    @cached_property
    def swing_axis(self) -> np.ndarray:
        """The main axis of the predicted motion, shape (3,), unit (its sign arbitrary)."""
        p = self.positions - self.positions.mean(axis=0)
        return np.linalg.eigh(p.T @ p)[1][:, -1]

    def velocity(self, t: float | np.ndarray) -> np.ndarray:
        """Velocity m/s at ``t`` (the spline's derivative; zero outside the samples): shape
        (3,) for a scalar ``t``, else (k, 3)."""
        return path_at(self.spline, t, derivative=1)


def grasp_times(path: PredictedPath, earliest_s: float, rule: str,
                timing_s: float = 0.1, max_sigma_m: float = np.inf) -> list[float]:
    """Candidate grasp times, best first; none where the prediction's own 1σ exceeds
    ``max_sigma_m``.

    ``period``: one period ahead, as the paper (Δt = T), or whole periods later when the arm
    needs longer, each then followed by the samples nearest it. ``slowest``: the samples at or
    after ``earliest_s`` ordered by the expected miss, the prediction's sigma plus the
    object's predicted speed times ``timing_s`` (how far off the arm's timing may be): a slow
    object forgives timing errors, and a nearer time is predicted better.
    """
    t0 = path.times_s[0]
    usable = path.times_s[(path.times_s >= earliest_s) & (path.sigma <= max_sigma_m)]
    if not len(usable):
        return []
    if rule == "period":
        k = max(1, int(np.ceil((usable[0] - t0) / path.period_s - 1e-9)))
        target = t0 + k * path.period_s
        return [float(t) for t in sorted(usable, key=lambda t: abs(t - target))]
    if rule != "slowest":
        raise ValueError(f"grasp time rule must be 'period' or 'slowest', got {rule!r}")
    speed = np.linalg.norm(path.velocity(usable), axis=1)
    miss = np.interp(usable, path.times_s, path.sigma) + timing_s * speed
    return [float(usable[i]) for i in np.argsort(miss, kind="stable")]


def motion_direction(path: PredictedPath, t: float) -> np.ndarray:
    """Unit direction, shape (3,), the object moves in as it arrives at ``t`` seconds
    (:func:`motion_directions`)."""
    return motion_directions(path, np.array([t]))[0]


def motion_directions(path: PredictedPath, t: np.ndarray) -> np.ndarray:
    """Unit directions, shape (k, 3), the object moves in as it arrives at each of ``t``
    (shape (k,), seconds); where it is (nearly) at rest, the main axis of its predicted
    swing, signed like the velocity 0.1 s before. One call for many times: the planner asks
    for dozens at once (:func:`~wavegrasp.planner.plan.plan_grasp`'s hint)."""
    v = path.velocity(t).reshape(-1, 3)
    speed = np.sqrt(np.einsum("ij,ij->i", v, v))
    moving = speed > 0.02
    out = np.empty_like(v)
    out[moving] = v[moving] / speed[moving, None]
    if not moving.all():
        before = path.velocity(t[~moving] - 0.1).reshape(-1, 3)
        axis = path.swing_axis
        out[~moving] = np.where((before @ axis >= 0)[:, None], axis, -axis)
    return out


#: _across: a face normal this near square to the motion (cos) is taken across it only.
SQUARE_COS = 0.05
#: No tool points up more steeply than this (its z's vertical part): never up from below,
#: where a tethered object's line is.
MAX_UP = 0.5


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v)


def perpendicular(d: np.ndarray, towards: np.ndarray) -> np.ndarray:
    """The unit vector ⟂ to the unit ``d`` closest to ``towards`` (any ⟂ one if parallel)."""
    ref = towards - (towards @ d) * d
    if np.linalg.norm(ref) < 1e-6:
        ref = cross(d, [0.0, 0.0, 1.0]) if abs(d[2]) < 0.9 else cross(d, [1.0, 0, 0])
    return _unit(ref)


def grasp_orientations(d: np.ndarray, axis: np.ndarray | None, preferred: np.ndarray,
                       count: int = 7, outwards: np.ndarray | None = None,
                       faces: list[np.ndarray] | None = None) -> list[np.ndarray]:
    """Tool orientations for a grasp of an object arriving along ``d`` (unit, world), best
    first: arrays, shape (3, 3), columns x (the jaws close along it), y, z (the tool points
    along it), world. A cylinder's (unit ``axis``) jaws always close across its axis.

    Two families. The paper's: the jaws close across the motion (x ⟂ d), so the final move
    along −d runs inside the open slot between them; the tool points anywhere from head-on
    against the motion (z = −d) to square to it (z ⟂ d, the side approach). The arm's own:
    given ``outwards`` (unit, from the shoulder to the object), the tool points along it, or
    level and turned from it, or reaching over an object high above the shoulder
    (:func:`_facing_frames`), with the jaws closing in any direction across it (and across
    the axis): an arm that looks across the motion, or along it, grasps the way it faces,
    and its final move is along the tool (see :func:`final_move`). Never up from below
    (:data:`MAX_UP`: where a tethered object's line is). The paper's family comes first;
    in each, those nearest the ``preferred`` z (unit) first. A box's jaws close on a pair
    of its ``faces`` (unit normals across its axis) within 30° of square to the motion (or
    the tool), across the motion (or the tool) and also square on the faces, the tool
    turned square to them: a jaw 30° off a face spans its corners, and an 11.5 x 9.8 cm
    box was wider than a 14 cm jaw opens in nearly every pose (random-109-024: 6428 such
    rejections, no plan in 204 predictions).
    """
    if faces is not None:
        closings = _across(faces, d)
    elif axis is not None and np.linalg.norm(cross(axis, d)) > 0.3:
        closings = [_unit(cross(axis, d))]
    else:  # a sphere, or a cylinder arriving end first: any closing direction across d
        e1 = cross(-preferred, d)
        e2 = cross(d, e1)
        closings = [np.cos(a) * e1 + np.sin(a) * e2 for a in np.radians([0, 45, 90, 135])]
    frames = []
    for x in closings:
        w = _unit(cross(x, d))
        for theta in np.radians(np.linspace(-90.0, 90.0, count)):
            R = _square(x, -np.cos(theta) * d + np.sin(theta) * w)
            if R[2, 2] < MAX_UP:
                frames.append(R)
    def best_first(frames: list[np.ndarray]) -> list[np.ndarray]:
        return sorted(frames, key=lambda R: -float(R[:, 2] @ preferred))

    facing = [] if outwards is None else _facing_frames(outwards, axis, d, faces)
    return best_first(frames) + best_first(facing)


def _across(faces: list[np.ndarray], v: np.ndarray) -> list[np.ndarray]:
    """The jaws' closing directions on the face normals (unit) within 30° of square to the
    unit ``v``: each normal made square to ``v`` (the jaw across the motion or the tool, as
    the family wants it), and the normal itself (the jaw square on the faces, the tool
    turned): a box that fits the jaw only square on may be taken so."""
    closings = []
    for f in faces:
        along = float(f @ v)
        if abs(along) < 0.5:
            closings.append(_unit(f - along * v))
            if abs(along) > SQUARE_COS:
                closings.append(f)
    return closings


def _square(x: np.ndarray, z: np.ndarray) -> np.ndarray:
    """The tool orientation, shape (3, 3), whose jaws close along the unit ``x`` and which
    points along ``z`` made square to it."""
    z = _unit(z - (z @ x) * x)
    return np.column_stack([x, cross(z, x), z])


def _facing_frames(outwards: np.ndarray, axis: np.ndarray | None, d: np.ndarray,
                   faces: list[np.ndarray] | None = None) -> list[np.ndarray]:
    """The arm's own family of :func:`grasp_orientations`: z along ``outwards``, along it
    without its part along a cylinder's axis, and turned ±30°, ±60° and ±90° about the
    vertical; where the object is too far above the shoulder to point at (``outwards`` up
    more than :data:`MAX_UP`), those level ones also tilted 30° and 60° down: the arm
    reaches over it. Per z the jaws close across the axis, on a box's faces, or (a sphere)
    in four directions, across the motion first. A 25 cm box 0.33 m above the shoulder and
    0.48 m from it, taken level, was reached or not by millimetres of its sway: 9 of 16
    predictions planned (random-197-029); reaching over it, every grasp time planned."""
    zs = [outwards]
    base = outwards if axis is None else outwards - (outwards @ axis) * axis
    if np.linalg.norm(base) > 0.3:  # not looking along a cylinder's axis
        base = _unit(base)
        up = np.array([0.0, 0.0, 1.0])
        level = [base] + [np.cos(a) * base + np.sin(a) * cross(up, base)
                          for a in np.radians([-30.0, 30.0, -60.0, 60.0, -90.0, 90.0])]
        zs += level
        if outwards[2] >= MAX_UP:  # the object is too far above to point at: reach over it
            zs += [np.cos(a) * z - np.sin(a) * up for a in np.radians([30.0, 60.0])
                   for z in level]
    frames = []
    for z in zs:
        z = _unit(z)
        if z[2] >= MAX_UP:
            continue
        if faces is not None:
            xs = _across(faces, z)
        elif axis is not None:
            if np.linalg.norm(cross(axis, z)) < 0.3:
                continue
            xs = [_unit(cross(axis, z))]
        else:
            first = perpendicular(z, d)
            other = cross(z, first)
            xs = [np.cos(a) * other + np.sin(a) * first for a in np.radians([0, 45, 90, 135])]
        frames += [R for R in (_square(x, z) for x in xs) if R[2, 2] < MAX_UP]
    return frames


def final_move(R: np.ndarray, d: np.ndarray) -> np.ndarray:
    """The unit direction the hand moves in its last move onto the object, for a tool at
    ``R`` (shape (3, 3), world) and an object arriving along ``d``: against the motion where
    that keeps the object inside the slot between the jaws (the paper's), else straight in
    along the tool."""
    against = -d + (d @ R[:, 0]) * R[:, 0]
    # Never backwards, palm first, out of the slot: a tool pointing the way the object
    # moves goes straight in after it.
    if np.linalg.norm(against) > 0.85 and against @ R[:, 2] > -0.2:
        return _unit(against)
    return R[:, 2]


def offset_direction(d: np.ndarray, z: np.ndarray, towards: np.ndarray) -> np.ndarray:
    """n of equation 8 for a tool pointing along ``z``: ⟂ to the motion ``d``, on the side
    the tool comes from (−z without its part along d); for a tool pointing head-on at the
    object, the side nearest ``towards``."""
    back = -(z - (z @ d) * d)
    return _unit(back) if np.linalg.norm(back) > 0.5 else perpendicular(d, towards)


def offsets(n: np.ndarray, move: np.ndarray, count: int) -> list[np.ndarray]:
    """``count`` directions for P_init's offset: ``n`` (unit) first, then ``n`` turned about
    the final ``move`` (unit) by ±60°, ±120° and 180°. Each keeps its angle to the final move,
    so the hand still comes in along it; another side of the object is what an arm too near
    or too far to come from the paper's side still reaches."""
    out = []
    for a in np.radians([0.0, 60.0, -60.0, 120.0, -120.0, 180.0][:count]):
        out.append(np.cos(a) * n + np.sin(a) * cross(move, n)
                   + (1.0 - np.cos(a)) * (move @ n) * move)
    return out


def waypoints(p_f: np.ndarray, n: np.ndarray, d: np.ndarray, alpha: float = 0.15,
              count: int = 4, beta: float = 0.03, final_m: float = 0.06,
              move: np.ndarray | None = None, final_step_m: float | None = None
              ) -> np.ndarray:
    """P_init, the intermediate P_i (equation 9, β_i bowing outwards along n, largest midway)
    and the pre-grasp point ``final_m`` back from P_f along the final ``move`` (unit; by
    default −d, against the object's motion ``d``), points evenly between it and P_f at
    most ``final_step_m`` apart (none if None), then P_f.

    Returns array, shape (count + 2 + m, 3), m the points between: the moves from the
    pre-grasp point on, the last m + 1, are along ``move``.
    """
    final_count = final_points(final_m, final_step_m)
    move = -d if move is None else move
    p_init = p_f + alpha * n
    pre = p_f - final_m * move
    points = [p_init]
    for i in range(1, count):
        s = i / count
        points.append(p_init + s * (pre - p_init) + beta * np.sin(np.pi * s) * n)
    points += [pre + s * (p_f - pre) for s in np.arange(final_count + 1) / (final_count + 1)]
    points.append(p_f)
    return np.array(points)


def final_points(final_m: float, final_step_m: float | None) -> int:
    """How many points :func:`waypoints` puts between the pre-grasp point and P_f."""
    if final_step_m is None:
        return 0
    return max(int(np.ceil(final_m / final_step_m - 1e-9)) - 1, 0)

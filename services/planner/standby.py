"""Where the idle arm waits between attempts, and its move there.

Joint values radians, in the arm's own model; ``T_world_base`` places its mount
``bravo_base_link`` in ``world``; positions metres.
"""

from __future__ import annotations

import numpy as np

from wavegrasp.arm import ArmModel
from wavegrasp.planner.approach import PredictedPath
from wavegrasp.planner.collision import Body, clearance, collides
from wavegrasp.planner.plan import (
    PlannerConfig,
    cheap_rejection,
    quickest_equivalent,
    tool_orientations,
)
from wavegrasp.planner.timing import Limits, sample_segment, segment


def standby_pose(arm: ArmModel, T_world_base: np.ndarray, seen: np.ndarray, body: Body,
                 margin_m: float = 0.08, cfg: PlannerConfig | None = None) -> np.ndarray:
    """Where the arm waits between attempts, radians, shape (n,): the first of
    :func:`standby_poses`, or the home pose before the object has been seen."""
    poses = standby_poses(arm, T_world_base, seen, body, margin_m, cfg=cfg)
    return poses[0] if poses else arm.q_home.copy()


def standby_poses(arm: ArmModel, T_world_base: np.ndarray, seen: np.ndarray, body: Body,
                  margin_m: float = 0.08, unsolved_s: float = 4.0, search_all: bool = False,
                  cfg: PlannerConfig | None = None) -> list[np.ndarray]:
    """Poses the arm may wait in between attempts, best first, radians, shape (n,) each.
    ``seen`` : array, shape (k, 3), metres, world: where the object's centroid has been
    lately (none yet: no poses).

    The candidates: the home pose turned to face the object, so an arm mounted at any yaw
    starts every approach from the object's side, and ready poses ``margin_m`` beyond the
    object's sway (its centroid's, and the object's reach towards the arm) with the tool
    pointing at it. Of those clear of the object, first the ones
    nearest (in time, joint by joint) to the grasps the planner tries at the sway's ends and
    middle (:func:`trial_grasps`), solved without leaving their branch of the arm's
    solutions (one that does not solve counts ``unsolved_s``, the predictions' reach), then
    the ones nearest to facing it. Facing an object above and behind the shoulder,
    the arm's elbow is on the branch where none of those grasps is within the joints'
    limits, and grasps from other seeds are the other branch, seconds away (random-7-003: 0
    of 12 predictions planned from facing, 12 of 12 from a ready pose). An object near the
    first joint's limits is otherwise waited for on the far side of them (grasps 5 rad away,
    4.3 s to reach). With none clear, whichever of facing and home keeps farthest from it.

    Where every trial grasp solves from facing, facing alone (the search takes about 0.5
    s), or with ``search_all`` facing first and the ready poses after it: solving is not
    planning, and a 13 cm sphere 0.76 m out, 0.49 m above the mount, planned from facing
    in 49 % of predictions and from four of the ready poses in all (random-103-005). ``cfg``:
    the planner's (default: its defaults)."""
    seen = np.asarray(seen, dtype=float).reshape(-1, 3)
    seen = seen[~np.isnan(seen).any(axis=1)]
    if not len(seen):
        return []
    T_base_world = np.linalg.inv(T_world_base)
    grasps = [T_base_world @ T for T in trial_grasps(arm, T_world_base, seen, body, cfg=cfg)]

    def gap(q: np.ndarray, seen_world: np.ndarray = seen, in_world: Body = body) -> float:
        return clearance(arm, T_world_base, q, seen_world, in_world)  # the seabed's in world

    seen = seen @ T_base_world[:3, :3].T + T_base_world[:3, 3]
    c = seen.mean(axis=0)
    sway = float(np.linalg.norm(seen - c, axis=1).max())
    facing = arm.facing(c)
    body = body.rotated(T_base_world[:3, :3])

    def solved(q: np.ndarray) -> tuple[int, float]:
        """How many trial grasps solve from q on its branch, and the mean time (s, at the
        joints' top speeds) to them, ``unsolved_s`` for one that does not."""
        times = []
        for T in grasps:
            q_f = arm.inverse(T, q, max_iter=40, restarts=-1)
            if q_f is not None:
                q_f = quickest_equivalent(arm, q_f, q)[0]
            times.append(unsolved_s if q_f is None else
                         float(np.max(np.abs(q_f - q) / arm.max_velocity)))
        return sum(t < unsolved_s for t in times), float(np.mean(times)) if times else 0.0

    clear = [(facing, solved(facing))] if gap(facing) > 0.01 else []
    first = [facing] if clear and clear[0][1][0] == len(grasps) else []
    if first and not search_all:
        return first
    clear = clear[len(first):]
    for u, back in _ready_directions(c - arm.shoulder):
        # The object's reach towards the arm, not its farthest along any axis: a 42 cm
        # bottle hanging neck down was waited for 25 cm above it, 2.6 s from every side
        # grasp at its middle (random-41-014, never planned).
        away = sway + body.extent(-u) + margin_m + back
        ready = arm.inverse_position(c - away * u, u, facing)
        if ready is not None and gap(ready[0]) > 0.01:
            clear.append((ready[0], solved(ready[0])))
    if not clear:
        return first or [max([facing, arm.q_home.copy()], key=gap)]
    clear.sort(key=lambda c: (c[1][1], float(np.max(np.abs(c[0] - facing) / arm.max_velocity))))
    return first + [q for q, _ in clear]


def trial_grasps(arm: ArmModel, T_world_base: np.ndarray, seen: np.ndarray, body: Body,
                 per_place: int = 6, cfg: PlannerConfig | None = None) -> list[np.ndarray]:
    """Grasp poses, shape (4, 4), world, the planner would try first for an object at the
    ends of its sway (arriving there outwards, where it slows: the grasp times the planner
    prefers) and in its middle: the first ``per_place`` orientations of
    :func:`~wavegrasp.planner.approach.grasp_orientations` at each that point away from the
    shoulder and fit the open jaw (:func:`~wavegrasp.planner.plan.cheap_rejection` with
    ``cfg``). seen : array, shape (k, 3), metres, world."""
    cfg = cfg if cfg is not None else PlannerConfig()
    c = seen.mean(axis=0)
    dev = seen - c
    axis = np.linalg.eigh(dev.T @ dev)[1][:, -1]
    along = dev @ axis
    shoulder = T_world_base[:3, :3] @ arm.shoulder + T_world_base[:3, 3]
    poses = []
    for p, d in ((seen[np.argmax(along)], axis), (seen[np.argmin(along)], -axis), (c, axis)):
        outwards, _, frames = tool_orientations(p, d, shoulder, body)
        kept = [R for R in frames if cheap_rejection(arm, R, outwards, body, cfg) is None]
        for R in kept[:per_place]:
            T = np.eye(4)
            T[:3, :3], T[:3, 3] = R, p
            poses.append(T)
    return poses


def standby_move(arm: ArmModel, T_world_base: np.ndarray, q_now: np.ndarray,
                 q_standby: np.ndarray, path: PredictedPath, now: float, body: Body,
                 cfg: PlannerConfig, via: list[np.ndarray] | tuple = (),
                 swept: np.ndarray | None = None
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray] | str:
    """The idle arm's move from ``q_now`` to ``q_standby`` (radians, shape (n,)), starting
    ``start_delay_s`` after ``now``, at rest at both ends: times (k,) s, q and qd (k, n); or
    why not ("already there", "cannot be timed", "collision" with the object on its
    predicted ``path``). An arm that starts facing away cannot reach a grasp within the
    prediction's horizon; from its standby it can. Where the direct move would sweep
    through the object, it stops on the way at the first of ``via`` (poses, radians, clear
    of it) that keeps the whole move clear: from one standby to its mirror image on the
    object's far side the first joint turns 3 rad through the object (random-7-034). An
    arm already in the object's way moves if it comes no nearer than staying would (the
    home pose of random-7-000 is 5 cm inside the sway: every move from it collided).

    Given ``swept`` (shape (m, 3), metres, world: where the object has been seen), the move
    keeps clear of the object at every one of them all the time, not of the ``path``: for
    a prediction not yet trusted (the predictor still warming up)."""
    if np.abs(q_standby - q_now).max() < cfg.standby_tolerance_rad:
        return "already there"
    zero = np.zeros(len(q_now))
    limits = Limits(arm.max_velocity, arm.max_acceleration, arm.max_jerk)
    for legs in [[q_now, q_standby]] + [[q_now, v, q_standby] for v in via]:
        start, parts = now + cfg.start_delay_s, []
        for a, b in zip(legs[:-1], legs[1:], strict=True):
            move = segment(a, zero, zero, b, zero, limits)
            if move is None:
                return "cannot be timed"
            times, q, qd = sample_segment(move, start, cfg.sample_dt_s)
            parts.append((times, q, qd) if not parts else (times[1:], q[1:], qd[1:]))
            start = times[-1]
        times, q, qd = (np.concatenate(x) for x in zip(*parts, strict=True))
        if swept is not None:
            if _clear_of(arm, T_world_base, q, q_now, swept, body, cfg.clearance_m):
                return times, q, qd
        elif not collides(arm, T_world_base, times, q, path, body, cfg.clearance_m, np.inf,
                          q_stay=q_now):
            return times, q, qd
    return "collision"


def _clear_of(arm: ArmModel, T_world_base: np.ndarray, q: np.ndarray, q_stay: np.ndarray,
              swept: np.ndarray, body: Body, need_m: float, every: int = 5) -> bool:
    """Do the poses ``q`` (k, n), radians, every ``every``-th and the last (samples 0.02 s
    apart: a tenth of a second), keep ``need_m`` from the object at any of ``swept`` (m, 3),
    metres, world, or at least as far as staying at ``q_stay`` would?"""
    need = min(need_m, clearance(arm, T_world_base, q_stay, swept, body))
    return clearance(arm, T_world_base, np.vstack([q[::every], q[-1:]]), swept, body) >= need


def _ready_directions(out: np.ndarray) -> list[tuple[np.ndarray, float]]:
    """Tool directions (unit, frame base_link) to wait in and how much farther back, metres,
    best first: from the shoulder towards the object (``out``), up to 0.2 m farther back,
    then level and turned up to 90° either way, then tilted 45° down: an object near the
    shoulder is reached from its side or from above."""
    up = np.array([0.0, 0.0, 1.0])
    level = out - (out @ up) * up
    level = level / np.linalg.norm(level) if np.linalg.norm(level) > 1e-6 else np.array(
        [1.0, 0.0, 0.0])
    side = np.cross(up, level)
    dirs = [(out / np.linalg.norm(out), back) for back in (0.0, 0.1, 0.2)]
    for tilt in np.radians([0.0, 45.0]):
        for turn in np.radians([0.0, 45.0, -45.0, 90.0, -90.0]):
            dirs.append((np.cos(tilt) * (np.cos(turn) * level + np.sin(turn) * side)
                         - np.sin(tilt) * up, 0.0))
    return dirs

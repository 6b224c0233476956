"""Plan one grasp: pick the time, generate candidates, reject the unreachable, the colliding
and the untimeable, and return the first that passes (candidates are ordered best first).

A candidate that cannot be timed tells how long the arm needs; when every candidate at a grasp
time was too slow, grasp times sooner than the quickest need are then skipped, so a failing
time costs one inverse kinematics each.

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
    final_move,
    final_points,
    grasp_orientations,
    grasp_times,
    motion_direction,
    motion_directions,
    offset_direction,
    offsets,
    perpendicular,
    waypoints,
)
from wavegrasp.planner.collision import Body, collides, hand_hits, jaw_lead
from wavegrasp.planner.timing import (
    Limits,
    least_duration,
    sample_path,
    sample_segment,
    segment,
    spline_path,
)


class PlannerConfig(BaseModel):
    grasp_time: str = Field("slowest", description="'slowest' or 'period' (the paper's Δt = T)")
    min_lead_s: float = Field(0.6, description="no grasp sooner than this after planning")
    start_delay_s: float = Field(0.25, description="time for the plan to be approved and sent")
    alpha_m: float = Field(0.08, description="P_init's distance from the object's surface")
    waypoint_count: int = 3
    beta_m: float = 0.02
    final_step_m: float = Field(0.02, description="where a finger would meet the object, "
                                "the final move is tried again through waypoints this far "
                                "apart: through its two ends alone the approach's joint "
                                "spline bowed the tool up to 2 cm off it, across the jaw (a "
                                "straight move takes about 0.1 s longer)")
    final_m: float = Field(0.05, description="the final move's least length; longer where the "
                           "open fingers would otherwise start it astride the object")
    jaw_margin_m: float = Field(0.01, description="the jaw's preshape: this wider than the "
                                "object on each side")
    clearance_m: float = Field(0.01, description="arm to object before the final move (the "
                               "gate's ε: it approves only while the mean error is below it)")
    cruise_mps: float = Field(0.4, description="tool speed assumed for the earliest grasp")
    approach_s: float = Field(0.8, description="time assumed for P_init to P_f")
    sample_dt_s: float = 0.02
    max_times: int = Field(40, description="grasp times tried, each with every orientation")
    max_candidates: int = Field(80, description="grasp poses checked in full (inverse "
                                "kinematics, timing, collisions) per prediction at most: it "
                                "bounds the planner's work per prediction")
    soon_s: float = Field(4.0, description="grasp times at most this long after planning "
                          "are searched first, then (each with max_candidates of its own) "
                          "the later ones: a later grasp only where none sooner plans. The "
                          "approach is open loop, trusting the forecast the whole way: with "
                          "the forecast's 4-6 s searched alike, plans went 5.1 s ahead "
                          "(median, was 3.3) and random-7-004 lost its first attempts")
    max_orientations: int = Field(8, description="tool orientations tried per grasp time (the "
                                  "paper's family first, then the arm's own)")
    min_outwards: float = Field(0.0, description="an arm does not reach round behind the object "
                                "to point back at itself: the least cosine between the tool's z "
                                "and the direction from the shoulder to the object")
    level_slack_deg: float | None = Field(15.0, description="a tool pointing back in space "
                                          "is still taken if in the level plane it points "
                                          "back no more than this past min_outwards (a tool "
                                          "reaching down onto an object above the shoulder); "
                                          "None: space alone decides")
    offset_tries: int = Field(4, description="directions n of P_init tried per grasp pose: "
                              "the paper's first, then turned about the final move")
    stage_tries: int = Field(4, description="starts of the move to P_init tried, spread "
                             "over the time the grasp leaves, before a collision on the way "
                             "refuses the candidate")
    max_joint_step_rad: float = Field(1.0, description="the most a joint may turn between "
                                      "neighbouring waypoints of the approach")
    standby_tolerance_rad: float = Field(0.3, description="an idle arm this near its standby "
                                         "(every joint) is not moved there before a plan")
    max_sigma_m: float | None = Field(None, description="grasp times at which the "
                                      "prediction's own 1σ exceeds this are not tried (None: "
                                      "half the jaw's widest opening: the object would as "
                                      "likely be outside the open jaw as inside it)")
    closed_loop: bool = Field(False, description="execution follows every new prediction "
                              "(:mod:`wavegrasp.planner.update`): a grasp time need not be "
                              "trusted when planned, only the forecast of its last "
                              "corrections, closed_loop_lead_s ahead")
    closed_loop_lead_s: float = Field(0.5, description="the lead at which the last "
                                      "corrections of a closed-loop approach are made: the "
                                      "prediction's 1-sigma there must be within max_sigma_m")
    ik_max_iter: int = 40
    ik_restarts: int = 0
    update_delay_s: float = Field(0.1, description="closed loop: an update takes over this "
                                  "long after the prediction it comes from (time to be "
                                  "approved and reach the arm)")
    splice_s: float = Field(0.2, description="closed loop: an update joins the moved approach "
                            "this long after it takes over (ruckig, from the arm's state)")
    update_min_m: float = Field(0.001, description="closed loop: a grasp point moved less "
                                "is not updated")
    update_max_m: float = Field(0.05, description="closed loop: nor one moved more (the "
                                "approach planned for it no longer fits: the gate aborts)")


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
    t_final: float = 0.0
    jaw_preshape_m: float = 0.0
    t_close: float = 0.0
    rejected: Counter = field(default_factory=Counter)
    #: Grasp poses (4, 4), world, that reached the full check, in order: this one's last.
    candidates: list[np.ndarray] = field(default_factory=list)
    #: The approach's spline: the times (k,) s it passes the waypoints ``points`` and the
    #: joint values (k, 6) there; and when the move to P_init starts and the approach
    #: begins (s). A closed-loop update moves them (:mod:`wavegrasp.planner.update`).
    knots: np.ndarray = field(default_factory=lambda: np.zeros(0))
    qs: np.ndarray = field(default_factory=lambda: np.zeros((0, 6)))
    move_s: tuple[float, float] = (0.0, 0.0)
    #: A closed-loop update: when, on the prediction it was made from, the arm would first
    #: touch the object before the final move (s; None: it keeps clear).
    t_contact: float | None = None


#: How finely :func:`_again` looks between the prediction's samples, and how far either
#: side of the time nearest the hint it tries, seconds.
AGAIN_STEP_S = 0.01
AGAIN_SPAN_S = 0.04


@dataclass(frozen=True)
class Hint:
    """Where, how and as the object moved when the last plan grasped it: ``T_grasp`` (4, 4),
    world; ``d`` (3,), unit, the motion there. The swing repeats, so the same phase of it a
    period later, from the same pose of the arm, is most likely feasible again."""

    T_grasp: np.ndarray
    d: np.ndarray

    @classmethod
    def of(cls, plan: Plan, path: PredictedPath) -> Hint:
        """The hint a ``plan`` made on ``path`` leaves for the next prediction."""
        return cls(plan.grasp_T_world, motion_direction(path, plan.t_grasp))


def plan_grasp(path: PredictedPath, now: float, arm: ArmModel, T_world_base: np.ndarray,
               q_now: np.ndarray, body: Body, cfg: PlannerConfig,
               hint: Hint | None = None) -> Plan | Counter:
    """The best feasible plan, or a Counter of why every candidate was rejected.

    body : the object's size and directions, metres, world. hint : the last plan's grasp,
    tried first (at the time the path comes back to it, in its orientation).
    """
    rejected: Counter = Counter()
    base_world = T_world_base[:3, 3]
    if np.linalg.norm(path.positions - base_world, axis=1).min() > arm.reach_m + 0.2:
        rejected["out of reach"] += 1
        return rejected
    # No grasp sooner than the arm could get there: from its tool to P_init at a modest
    # Cartesian speed, then the approach itself.
    tool_world = (T_world_base @ arm.forward(q_now))[:3, 3]
    reach_time = np.linalg.norm(path.positions - tool_world, axis=1).min() / cfg.cruise_mps
    start = now + cfg.start_delay_s
    earliest = start + max(cfg.min_lead_s, reach_time + cfg.approach_s)
    shoulder = T_world_base[:3, :3] @ arm.shoulder + base_world
    need, tried, used = 0.0, 0, 0
    candidates: list[np.ndarray] = []
    max_sigma = cfg.max_sigma_m if cfg.max_sigma_m is not None else arm.jaw_max_opening_m / 2
    times = grasp_times(path, earliest, cfg.grasp_time, max_sigma_m=max_sigma)
    late = float(np.interp(now + cfg.closed_loop_lead_s, path.times_s, path.sigma))
    if cfg.closed_loop and late <= max_sigma:
        # Corrected on the way, the grasp goes where the object is forecast a moment before
        # it: JONSWAP wave 1's forecast of the buoy 1.5 s ahead is 74 mm uncertain (median),
        # 0.5 s ahead 42 mm, and open loop's limit on the grasp time (70 mm) left 722 of 801
        # of its predictions unplanned. The times the forecast trusts still come first:
        # ranked with them, the less trusted (at a turning point, "slowest") were taken
        # before them and the tank's trials grew too long (4 s leads instead of 2.8). None
        # the forecast does not trust at all (an infinite sigma).
        times += [t for t in grasp_times(path, earliest, cfg.grasp_time,
                                         max_sigma_m=np.finfo(float).max) if t not in times]
    if not times and (path.times_s >= earliest).any():
        rejected["prediction too uncertain"] += 1
        return rejected

    def attempt(t_g: float, R: np.ndarray, p_f: np.ndarray, d: np.ndarray, here: Body,
                outwards: np.ndarray, towards: np.ndarray) -> Plan | tuple[str, float] | None:
        """The grasp at ``t_g`` in orientation ``R``: the plan, why not, or None where a
        cheap rejection refused it (not a try)."""
        T_grasp = np.eye(4)
        T_grasp[:3, :3], T_grasp[:3, 3] = R, p_f
        reason = cheap_rejection(arm, R, outwards, here, cfg) or (
            "collision" if hand_hits(arm, T_grasp, here) else None)
        if reason:
            rejected[reason] += 1
            return None
        candidates.append(T_grasp)
        result = _candidate(path, now, t_g, T_grasp, offset_direction(d, R[:, 2], towards), d,
                            arm, T_world_base, q_now, body, cfg)
        if isinstance(result, Plan):
            result.rejected, result.candidates = rejected, candidates
            return result
        rejected[result[0]] += 1
        return result

    # The last plan's grasp first, in its own orientation, where the path comes back to it.
    hint_need = 0.0
    for t_g in _again(path, times, hint) if hint is not None and times else []:
        if t_g < start + hint_need:
            continue
        p_f, d, here = path.at(t_g), motion_direction(path, t_g), body.at(t_g)
        outwards, towards, _ = tool_orientations(p_f, d, shoulder, here)
        result = attempt(t_g, hint.T_grasp[:3, :3], p_f, d, here, outwards, towards)
        if isinstance(result, Plan):
            return result
        if result is not None and result[0] == "cannot be timed":
            hint_need = max(hint_need, result[1])
    soon = [t for t in times if t <= now + cfg.soon_s]
    later = [t for t in times if t > now + cfg.soon_s]
    first_later = later[0] if later else None
    for t_g in soon + later:
        if t_g == first_later:  # the later times' own budget
            tried, used = 0, 0
        if t_g < start + need or tried == cfg.max_times or used == cfg.max_candidates:
            continue
        p_f, d = path.at(t_g), motion_direction(path, t_g)
        if np.linalg.norm(p_f - shoulder) > arm.reach_m:  # no orientation reaches it: no IK
            rejected["out of reach"] += 1
            continue
        quickest, tried_here = np.inf, 0
        here = body.at(t_g)  # as it will be turned then
        outwards, towards, frames = tool_orientations(p_f, d, shoulder, here)
        for R in frames:
            if tried_here == cfg.max_orientations or used == cfg.max_candidates:
                break
            result = attempt(t_g, R, p_f, d, here, outwards, towards)
            if result is None:
                continue
            if isinstance(result, Plan):
                return result
            tried_here += 1
            tried += tried_here == 1
            used += 1
            reason, needed = result
            # Only when every pose at this time was too slow does a time this soon fail for
            # all: a pose that failed otherwise might have been quicker.
            quickest = min(quickest, needed if reason == "cannot be timed" else 0.0)
        if np.isfinite(quickest):
            need = max(need, quickest)
    if not rejected:
        rejected["no grasp time in the prediction"] += 1
    return rejected


def _again(path: PredictedPath, times: list[float], hint: Hint) -> list[float]:
    """Times at which to try the ``hint``'s grasp again: for each period, soonest first,
    the time the object comes back nearest where and as it moved then (a centimetre of
    position weighs as much as 6 degrees of direction), then the times either side of it
    within ``AGAIN_SPAN_S``, nearest first, in steps of ``AGAIN_STEP_S``. The swing brings
    the object back a period later, but rarely on one of the prediction's samples, and
    rarely to within a centimetre of where it was: a grasp that plans in only a few
    hundredths of a second of the swing is missed by samples a tenth apart (random-179-000's
    box planned 10 of 159 predictions), and by the time nearest the hint where the path
    comes back 2-3 cm from it (random-193-015's box: 6 predictions in a row planned none;
    the hint's grasp plans 0.03-0.05 s before the nearest time, in two of three periods).
    The last plan's grasp time comes nearer with each prediction until the arm can no longer
    make it, and then the next period's is the one."""
    def miss(t: np.ndarray) -> np.ndarray:
        d = motion_directions(path, t)
        return (np.linalg.norm(path.at(t) - hint.T_grasp[:3, 3], axis=1)
                + 0.1 * np.linalg.norm(d - hint.d, axis=1))

    grid = np.array(times)
    at_grid = miss(grid)
    step = float(np.median(np.diff(path.times_s)))
    best: list[float] = []
    for i in np.argsort(at_grid, kind="stable"):
        if at_grid[i] > at_grid.min() + 0.03:  # no other period comes back to it
            break
        if all(abs(grid[i] - t) > path.period_s / 2 for t in best):
            near = grid[i] + np.arange(-step, step + 1e-9, AGAIN_STEP_S)
            near = near[(near >= grid.min()) & (near <= path.times_s[-1])]
            best.append(float(near[np.argmin(miss(near))]))
    side = AGAIN_STEP_S * np.arange(1, round(AGAIN_SPAN_S / AGAIN_STEP_S) + 1)
    shifts = np.concatenate([[0.0], np.ravel(np.column_stack([-side, side]))])
    return [float(t + o) for t in sorted(best) for o in shifts
            if grid.min() <= t + o <= grid.max()]


def tool_orientations(p_f: np.ndarray, d: np.ndarray, shoulder: np.ndarray, body: Body
                      ) -> tuple[np.ndarray, np.ndarray, list[np.ndarray]]:
    """The tool orientations, shape (3, 3), world, to try for a grasp at ``p_f`` (metres,
    world) of ``body`` arriving along ``d`` (unit), best first (:func:`grasp_orientations`):
    the paper's side approach from above the object and the arm's side of it first. Returns
    them with ``outwards`` (unit, the shoulder to P_f) and the ``towards`` they prefer."""
    outwards = (p_f - shoulder) / np.linalg.norm(p_f - shoulder)
    towards = np.array([0.0, 0.0, 1.0]) - 0.5 * outwards
    return outwards, towards, grasp_orientations(d, body.axis, -perpendicular(d, towards),
                                                 outwards=outwards, faces=body.faces)


def cheap_rejection(arm: ArmModel, R: np.ndarray, outwards: np.ndarray, body: Body,
                    cfg: PlannerConfig) -> str | None:
    """Why a tool orientation ``R`` (3, 3) is refused before any inverse kinematics, or
    None: it points back at the arm (:func:`points_back`), or the object is wider across
    its jaws than they open."""
    if points_back(R[:, 2], outwards, cfg.min_outwards, cfg.level_slack_deg):
        return "points back at the arm"
    if 2.0 * body.extent(R[:, 0]) > arm.jaw_max_opening_m:
        return "wider than the jaw"
    return None


def points_back(z: np.ndarray, outwards: np.ndarray, min_outwards: float,
                level_slack_deg: float | None) -> bool:
    """Whether a tool pointing along ``z`` (unit, world) points back at the arm whose
    shoulder is behind the object along ``outwards`` (unit, the shoulder to the object):
    its cosine with ``outwards`` is below ``min_outwards`` in space, and in the level plane
    by more than ``level_slack_deg`` too (None: in space alone). A tool pointing down onto
    an object above the shoulder points back in space but not round behind it: so refused,
    a 14 cm sphere 13 cm above the shoulder planned none of 113 predictions, where a
    brute-force search found 11 poses that planned, 10 of them within 30 degrees of straight
    down (random-149-022). The slack keeps a tool pointing down, or level across the way
    out, from being refused on a millimetre of the object's sway."""
    if z @ outwards >= min_outwards:
        return False
    if level_slack_deg is None:
        return True
    level_z, level_out = z[:2], outwards[:2]
    norm_z, norm_out = np.linalg.norm(level_z), np.linalg.norm(level_out)
    if norm_z < 1e-9:  # straight down: never round behind the object
        return False
    if norm_out < 1e-9:  # the object straight above or below the shoulder
        return True
    slack = np.sin(np.radians(level_slack_deg))
    return bool(level_z @ level_out / (norm_z * norm_out) < min_outwards - slack)


def quickest_equivalent(arm: ArmModel, q_f: np.ndarray, q_now: np.ndarray
                        ) -> tuple[np.ndarray, bool]:
    """Of the joint values (radians, shape (n,)) that make the grasp ``q_f`` makes, the one
    the arm reaches soonest from ``q_now`` at its joints' top speeds (the slowest joint's
    time, then all joints'), and whether its jaws are swapped: ``q_f``, its wrist turned
    over (:meth:`~wavegrasp.arm.ArmModel.wrist_twins`: the same tool pose), and either
    with the last joint turned by pi (the same grasp, jaws swapped). Inverse kinematics from
    ``q_now`` often lands on the wrist's other branch: grasps of a box near the shoulder
    turned the wrist's pitch 3.7 rad, 1.9 s at its top speed, where the twin turned it 0.2
    (random-73-009)."""
    options = []
    for twin in arm.wrist_twins(q_f):
        for turn in (0.0, np.pi, -np.pi):
            q = twin.copy()
            q[-1] += turn
            if arm.lower[-1] <= q[-1] <= arm.upper[-1]:
                t = np.abs(q - q_now) / arm.max_velocity
                options.append((float(t.max()), float(t.sum()), turn != 0.0, q))
    _, _, swapped, q = min(options, key=lambda o: (o[0], o[1]))
    return q, swapped


def _candidate(path: PredictedPath, now: float, t_g: float, T_grasp: np.ndarray,
               n_paper: np.ndarray, d: np.ndarray, arm: ArmModel, T_world_base: np.ndarray,
               q_now: np.ndarray, body: Body, cfg: PlannerConfig
               ) -> Plan | tuple[str, float]:
    """One grasp pose at one time: the plan, or why not and (if it cannot be timed) how long
    the arm needs from ``now + start_delay_s`` to the grasp."""
    limits = Limits(arm.max_velocity, arm.max_acceleration, arm.max_jerk)
    T_base_world = np.linalg.inv(T_world_base)
    q_f = arm.inverse(T_base_world @ T_grasp, q_now, max_iter=cfg.ik_max_iter,
                      restarts=cfg.ik_restarts)
    if q_f is None:
        return "unreachable", np.inf
    q_f, swapped = quickest_equivalent(arm, q_f, q_now)
    if swapped:
        T_grasp = T_grasp @ np.diag([-1.0, -1.0, 1.0, 1.0])
    t_start = now + cfg.start_delay_s
    # Cheap test before the other waypoints: could the arm even be at P_f in time?
    direct = segment(q_now, np.zeros(6), np.zeros(6), q_f, np.zeros(6), limits)
    if direct is None:
        return "cannot be timed", np.inf
    if t_start + direct.duration > t_g:
        return "cannot be timed", direct.duration
    move = final_move(T_grasp[:3, :3], d)
    # The paper's approach first: from P_init α beyond the object's surface and a final
    # move of 5 cm, both measured from the tool point, while the open fingers reach 6 cm
    # ahead of it: waiting at P_init their tips are 2 cm from the object, and when the final
    # move starts they are often astride it already, where a jaw only a little wider than
    # the object leaves no room for the approach's clearance. Then, if that collides, one
    # measured from the fingers (not always: it is longer). An 11 cm bottle below the arm
    # (tests/test_planner.py): 0 of 11 phases planned before, 8 after.
    # Each first with the paper's spline through the final move's two ends (the quickest),
    # then, if a finger would meet the object, through points along it (straight, slower).
    for clear in (False, True):
        for step in (None, cfg.final_step_m):
            result = _approach(path, now, t_g, T_grasp, q_f, n_paper, d, move, clear, step,
                               arm, T_world_base, q_now, body, cfg)
            if isinstance(result, Plan) or result[0] != "object would hit a finger":
                break
        if isinstance(result, Plan) or result[0] != "collision":
            break
    return result


def _approach(path: PredictedPath, now: float, t_g: float, T_grasp: np.ndarray,
              q_f: np.ndarray, n_paper: np.ndarray, d: np.ndarray, move: np.ndarray,
              clear: bool, final_step_m: float | None, arm: ArmModel,
              T_world_base: np.ndarray, q_now: np.ndarray, body: Body, cfg: PlannerConfig
              ) -> Plan | tuple[str, float]:
    """:func:`_candidate`'s grasp pose with the arm at ``q_f`` there, approached along the
    final ``move`` (unit, world): the timed, checked plan or why not. ``clear``: α and the
    final move's start measured from the open fingers, not the tool point;
    ``final_step_m``: the final move's waypoints at most this apart (None: its ends only)."""
    here = body.at(t_g)
    R = T_grasp[:3, :3]
    final_m = cfg.final_m
    if clear:
        final_m = max(final_m, here.extent(move) + jaw_lead(arm, R.T @ move) + cfg.clearance_m)
    limits = Limits(arm.max_velocity, arm.max_acceleration, arm.max_jerk)
    T_base_world = np.linalg.inv(T_world_base)
    p_f = T_grasp[:3, 3]
    t_start = now + cfg.start_delay_s
    solved: dict[bytes, np.ndarray | None] = {}  # the points every n shares, solved once
    for n in offsets(n_paper, move, cfg.offset_tries):
        alpha = cfg.alpha_m + here.extent(n) + (jaw_lead(arm, R.T @ -n) if clear else 0.0)
        points = waypoints(p_f, n, d, alpha, cfg.waypoint_count, cfg.beta_m, final_m, move,
                           final_step_m)
        qs = approach_joints(arm, T_base_world @ T_grasp, T_base_world, points, q_f, cfg,
                             solved)
        if qs is not None:
            break
    else:
        return "approach unreachable", np.inf
    # Stage at P_init (ruckig, time-optimal), wait there, then the paper's cubic spline
    # through the waypoints, timed to end at P_f exactly at the grasp time.
    pre = segment(q_now, np.zeros(6), np.zeros(6), qs[0], np.zeros(6), limits)
    if pre is None:
        return "cannot be timed", np.inf
    least = pre.duration + least_duration(qs, limits)
    if t_start + least > t_g:  # before timing the spline
        return "cannot be timed", least
    approach = spline_path(qs, limits)
    d_path = approach.duration
    if t_start + pre.duration + d_path > t_g:
        return "cannot be timed", pre.duration + d_path
    t_app, q_app, v_app = sample_path(approach, t_g - d_path, cfg.sample_dt_s)
    t_app[-1] = t_g
    final_from = t_g - d_path + approach.spline.x[-2 - final_points(final_m, final_step_m)]
    slack = t_g - d_path - t_start - pre.duration
    # The move to P_init goes straight in joint space and often sweeps the hand through the
    # object's swing (most collisions of random-103-003): where the grasp leaves time to
    # wait, the arm waits at its standby instead and passes once the object is elsewhere.
    # The approach, the same whatever the start, is checked once.
    if collides(arm, T_world_base, t_app, q_app, path, body, cfg.clearance_m, final_from):
        return "collision", 0.0
    dt = cfg.sample_dt_s
    for delay in stage_delays(slack, path.period_s, cfg.stage_tries):
        t_pre, q_pre, v_pre = sample_segment(pre, t_start + delay, dt)
        t_wait = np.arange(t_start, t_pre[0] - dt / 2, dt)
        if t_pre[-1] > t_app[0] - dt / 2:  # it ends at rest at P_init as the approach starts
            t_pre, q_pre, v_pre = t_pre[:-1], q_pre[:-1], v_pre[:-1]
            t_hold = np.zeros(0)
        else:
            t_hold = np.arange(t_pre[-1] + dt, t_app[0] - dt / 2, dt)
        t_before = np.concatenate([t_wait, t_pre, t_hold])
        q_before = np.vstack([np.tile(q_now, (len(t_wait), 1)), q_pre,
                              np.tile(qs[0], (len(t_hold), 1))])
        if not collides(arm, T_world_base, t_before, q_before, path, body, cfg.clearance_m,
                        final_from):
            break
    else:
        return "collision", 0.0
    times = np.concatenate([t_before, t_app])
    q = np.vstack([q_before, q_app])
    qd = np.vstack([np.zeros((len(t_wait), 6)), v_pre, np.zeros((len(t_hold), 6)), v_app])
    tool = (T_world_base @ arm.forward_batch(q))[:, :3, 3]
    sigma = float(np.interp(t_g, path.times_s, path.sigma))
    speed = float(np.linalg.norm(path.velocity(t_g)))
    confidence = float(np.exp(-sigma / 0.01) / (1.0 + speed))
    # Narrow the jaw for the final move and start closing just in time: a jaw opened wide
    # closes too slowly for an object that turns back right after the grasp time. The
    # opening also takes in how far the object moves along the closing direction x while
    # the fingers are either side of it (nearly nothing when they close across the motion).
    x = T_grasp[:3, 0]
    width = 2.0 * here.extent(x)
    rel = path.at(np.minimum(times, path.times_s[-1])) - tool  # object from the tool point
    # The fingers span from their roots behind the tool point to their tips ahead of it: a
    # fixed finger's thickness missed the tips reaching round the object 6 cm ahead.
    along, u = rel @ move, T_grasp[:3, :3].T @ move
    astride = ((times >= final_from) & (along <= here.extent(move) + jaw_lead(arm, u))
               & (along >= -here.extent(move) - jaw_lead(arm, -u)))
    need = jaw_needs(body, times[astride], rel[astride], x, width)
    if need.max() > arm.jaw_max_opening_m:
        return "object would hit a finger", 0.0
    preshape = min(arm.jaw_max_opening_m, need.max() + 2.0 * cfg.jaw_margin_m)
    t_close = jaw_closing(preshape, width, t_g, times[astride], need, arm.jaw_closing_mps)
    return Plan(t_start, t_g, times, q, qd, tool, points, T_grasp, -n, confidence, final_from,
                preshape, t_close, knots=t_g - d_path + approach.spline.x, qs=qs,
                move_s=(float(t_pre[0]) if len(t_pre) else float(t_app[0]), float(t_app[0])))


def jaw_needs(body: Body, times: np.ndarray, rel: np.ndarray, x: np.ndarray,
              width: float) -> np.ndarray:
    """The jaw's least opening, metres, at each of ``times`` (k,) s while the fingers are
    either side of the object (``rel`` (k, 3): the object from the tool point, world; ``x``:
    the closing direction), the object as it is turned then and off the jaw's middle.
    ``width``: the opening at the grasp, for no time astride."""
    if not len(times):
        return np.array([width])
    return np.array([2.0 * (body.at(t).extent(x) + abs(float(r @ x)))
                     for t, r in zip(times, rel, strict=True)])


def jaw_closing(preshape: float, width: float, t_g: float, times: np.ndarray,
                need: np.ndarray, speed_mps: float) -> float:
    """When the jaw starts closing from ``preshape`` (metres) at ``speed_mps``: just in time
    to meet the object's ``width`` at the grasp time ``t_g`` (s), unless that would narrow
    it below what the object ``need`` s (metres) at ``times`` before ``t_g``; then as late as
    that asks. Closing just in time, the fingertips met a box 9 cm ahead of the tool point
    still sweeping 2 cm across the jaw (random-139-013)."""
    t_close = t_g - (preshape - width) / speed_mps
    before = times < t_g
    if before.any():
        t_close = max(t_close, float(np.max(times[before] - (preshape - need[before])
                                            / speed_mps)))
    return t_close


def stage_delays(slack_s: float, period_s: float, tries: int) -> np.ndarray:
    """When to start the move to P_init, seconds after the plan's start: at once, then up to
    ``tries`` - 1 later starts spread over the ``slack_s`` the grasp time leaves, within one
    ``period_s`` of the swing (a period later the object is where it was). Where the slack
    is longer than that, the same spread again ending at the latest start: an arm that
    starts early holds at P_init for the rest of the slack while the object swings past it.
    A 31 cm box swinging 27 cm towards and away from the arm could only be grasped where it
    came nearest the shoulder: grasps there more than a period ahead all collided on the
    hold, and the planner found one for 10 of 159 predictions (random-179-000)."""
    if tries < 2:
        return np.zeros(1)
    span = min(max(slack_s, 0.0), period_s * (tries - 1) / tries)
    if span < 0.05:
        return np.zeros(1)
    early = np.linspace(0.0, span, tries)
    late = early + slack_s - span
    return np.concatenate([early, late[late > span + 0.05]])


def approach_joints(arm: ArmModel, T_base_grasp: np.ndarray, T_base_world: np.ndarray,
                    points: np.ndarray, q_f: np.ndarray, cfg: PlannerConfig,
                    solved: dict[bytes, np.ndarray | None]) -> np.ndarray | None:
    """Joint values (k, n) at the waypoints ``points`` (k, 3), world, the tool held as in
    the grasp; solved from the grasp back to P_init, each seeding the next, so neighbours
    stay on one branch. None if one is unreachable or only on another branch. ``solved``
    keeps the solutions of points reached the same way before (the same P_f and pre-grasp
    point for every offset n)."""
    qs, seed, prefix = [], q_f, b""
    for p in points[::-1]:
        prefix += p.tobytes()
        if prefix not in solved:
            T = T_base_grasp.copy()
            T[:3, 3] = (T_base_world @ np.append(p, 1.0))[:3]
            # From the neighbour alone: a solution from another seed would be on another
            # branch, refused below anyway (on the tank every waypoint solved came from it).
            solved[prefix] = arm.inverse(T, seed, max_iter=cfg.ik_max_iter, restarts=-1)
        q = solved[prefix]
        # Waypoints a few centimetres apart need no joint to swing far: one that does has
        # jumped to another branch of the arm's solutions, a detour, not the approach.
        if q is None or np.abs(q - seed).max() > cfg.max_joint_step_rad:
            return None
        qs.append(q)
        seed = q
    return np.array(qs[::-1])

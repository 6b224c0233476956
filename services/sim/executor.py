"""Execute an approved plan in the simulated scene and judge the grasp physically.

Rules (the README lists them too):

- **success**: after the jaw closes at the grasp time and settles, both fingers touch the object
  and it stays between them for ``hold_s`` while its drive keeps pulling it along its path:
  at the end both touch it and its centroid lies, along the approach, between the palm and
  the fingertips (pulled against the palm, it is held still).
- Otherwise the first rule that holds names the failure:
  1. **abrupt change**: the prediction the plan came from still held when the plan was
     approved (within ``abrupt_m`` / 2 of the object), then, before the grasp time, the
     object strayed more than ``abrupt_m`` from it (whatever went wrong next, it caused);
  2. **collision**: before the jaw closed, an arm link other than the fingers touched the
     object, or a finger did before the final move began, or any link touched the tether;
  3. **unreachable**: at the grasp time the tool was more than ``reach_tol_m`` from the
     planned grasp point (the arm could not follow its trajectory);
  4. **timing**: the object was not at the grasp point at the grasp time, but it passed
     within ``pass_tol_m`` of it within ``timing_window_s`` before or after (the arm arrived
     early or late);
  5. **prediction**: the object came nowhere near the grasp point (the prediction was wrong);
  6. **other**: the object was there on time and still not held (it slipped).

Times are seconds on the recording clock; positions metres, ``world``.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from pydantic import BaseModel, Field

from wavegrasp.planner.timing import Limits, sample_segment, segment
from wavegrasp.schemas import GraspPlan
from wavegrasp.schemas.path import interpolate_path
from wavegrasp.sim.world import SimWorld


class JudgeConfig(BaseModel):
    settle_s: float = Field(0.6, description="after the grasp time, for the jaw to close")
    hold_s: float = Field(1.0, description="the object must stay held this long")
    reach_tol_m: float = 0.02
    pass_tol_m: float = 0.015
    timing_window_s: float = 0.5
    abrupt_m: float = 0.02
    closed_m: float = Field(0.0, description="the jaw's commanded opening when closing")
    retreat_m: float = Field(0.08, description="an aborted attempt backs the tool out this "
                             "far along its approach before it returns to standby")


@dataclass
class Attempt:
    """An approved plan: times (k,) s; q, qd (k, n) rad, rad/s; grasp point p_f (3,);
    final_from: when the final move, into P_f, begins; the jaw narrows to ``jaw_preshape_m``
    for the final move and starts closing at ``t_close`` (so it meets the object at the
    grasp time rather than a third of a second later)."""

    plan_id: str
    times: np.ndarray
    q: np.ndarray
    qd: np.ndarray
    t_grasp: float
    p_f: np.ndarray
    final_from: float
    jaw_preshape_m: float
    t_close: float
    #: The prediction the plan came from: times (m,) s and positions (m, 3); and when the
    #: plan was approved (recording s). Without them abrupt changes are not told apart.
    predicted: tuple[np.ndarray, np.ndarray] | None = None
    approved_at: float | None = None
    #: Where the arm waits after the attempt, shape (n,), radians; None: its home pose.
    standby: np.ndarray | None = None

    @classmethod
    def from_message(cls, plan: GraspPlan, joint_names: list[str]) -> Attempt:
        """From ``wavegrasp/planner/plan``; raises ValueError naming what is missing."""
        if not plan.joint_trajectory:
            raise ValueError(f"plan {plan.plan_id}: no joint_trajectory")
        if plan.joint_names != joint_names:
            raise ValueError(f"plan {plan.plan_id}: joint_names {plan.joint_names} are not "
                             f"the arm's {joint_names}")
        s = plan.joint_trajectory
        for k, sample in enumerate(s):
            for name in ("positions", "velocities"):  # velocities may be left out
                n = len(getattr(sample, name))
                if n != len(joint_names) and (n or name == "positions"):
                    raise ValueError(f"plan {plan.plan_id}: joint_trajectory sample {k} has {n} "
                                     f"{name}, the arm {len(joint_names)} joints")
        if plan.standby and len(plan.standby) != len(joint_names):
            raise ValueError(f"plan {plan.plan_id}: standby has {len(plan.standby)} positions, "
                             f"the arm {len(joint_names)} joints")
        t_grasp = plan.t_grasp_ns * 1e-9
        p = plan.grasp.position
        return cls(plan.plan_id, np.array([x.t_ns for x in s]) * 1e-9,
                   np.array([x.positions for x in s]),
                   np.array([x.velocities or [0.0] * len(joint_names) for x in s]), t_grasp,
                   np.array([p.x, p.y, p.z]),
                   (plan.t_final_ns or plan.t_grasp_ns) * 1e-9,
                   plan.jaw_preshape_m or 0.0,
                   (plan.t_close_ns or plan.t_grasp_ns) * 1e-9,
                   standby=np.array(plan.standby) if plan.standby else None)


@dataclass
class Result:
    plan_id: str
    success: bool
    failure: str | None
    evidence: dict[str, float | str | bool] = field(default_factory=dict)
    aborted: bool = False


class Executor:
    """Runs one attempt at a time in ``world``; :meth:`advance` moves everything to a time."""

    def __init__(self, world: SimWorld, cfg: JudgeConfig | None = None) -> None:
        self.world, self.cfg = world, cfg or JudgeConfig()
        self.attempt: Attempt | None = None
        self._truth: list[tuple[float, np.ndarray]] = []
        self._touched: dict[str, float] = {}
        self._tool_at_grasp: np.ndarray | None = None
        self._closing = self._preshaped = False
        self._return: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None
        self._started_at = 0.0
        names = world.link_names
        self._finger_names = {names[i] for i in world.finger_links}
        self._names = names
        # Along the approach (tool z), from the palm to the fingertips, metres from the grasp
        # point: an object whose centroid is there, both fingers on it, is held.
        start, end, _radius = world.arm.jaw_capsules
        z = np.concatenate([start[:, 2], end[:, 2]])
        self._jaw_depth = (float(z.min()), float(z.max()))

    @property
    def busy(self) -> bool:
        """Executing an attempt or returning to standby."""
        return self.attempt is not None or self._return is not None

    @property
    def returning(self) -> bool:
        """Moving to a standby pose, after an attempt or as the planner asked."""
        return self._return is not None

    def start(self, attempt: Attempt) -> None:
        if self.busy:
            raise ValueError(f"plan {attempt.plan_id}: another is executing")
        self.attempt = attempt
        self._started_at = self.world.time_s  # approved (updates do not move it)
        self._truth, self._touched = [], {}
        self._tool_at_grasp, self._closing, self._preshaped = None, False, False
        self.world.set_jaw(self.world.arm.jaw_max_opening_m)
        self.world.tether_touches()  # those on the way back from the last attempt are not its

    def advance(self, t_s: float, position: np.ndarray, quat_xyzw: np.ndarray) -> Result | None:
        """Drive the object to its pose at ``t_s``, the arm along its plan, step the world to
        ``t_s``; returns the attempt's result once it is judged."""
        w = self.world
        w.drive_object(position, quat_xyzw)
        a = self.attempt
        w.watch_tether = a is not None and w.time_s < a.t_grasp  # read below only then
        if a is None:
            self._follow_return(t_s)
            w.step_to(t_s)
            return None
        self._truth.append((t_s, position.copy()))
        if t_s <= a.times[-1]:
            k = min(max(np.searchsorted(a.times, t_s), 0), len(a.times) - 1)
            q = np.array([np.interp(t_s, a.times, a.q[:, j]) for j in range(a.q.shape[1])])
            w.command_arm(q, a.qd[k] if a.times[0] <= t_s < a.times[-1] else np.zeros(len(q)))
        w.step_to(t_s)
        if w.time_s < a.t_grasp:
            for link in w.contacts():
                name = self._names[link]
                if name in self._finger_names and w.time_s >= a.final_from:
                    continue  # the object entering the jaw in the final move
                self._touched.setdefault(name, a.t_grasp - w.time_s)
            for link in w.tether_touches():
                self._touched.setdefault(f"{self._names[link]} on the tether",
                                         a.t_grasp - w.time_s)
        # A jaw that began closing before its final move keeps closing: the preshape is for
        # a jaw still open wide, and reopening it there let the object swing through.
        if (not self._preshaped and not self._closing and a.jaw_preshape_m > 0
                and w.time_s >= a.final_from):
            w.set_jaw(a.jaw_preshape_m)
            self._preshaped = True
        if not self._closing and w.time_s >= a.t_close:
            w.set_jaw(self.cfg.closed_m)
            self._closing = True
        if self._tool_at_grasp is None and w.time_s >= a.t_grasp:
            self._tool_at_grasp = w.tool_position()
        if w.time_s >= a.t_grasp + self.cfg.settle_s + self.cfg.hold_s:
            return self._finish(self._judge())
        return None

    def _judge(self) -> Result:
        a, w, cfg = self.attempt, self.world, self.cfg
        assert a is not None and self._tool_at_grasp is not None
        touching = {self._names[i] for i in w.contacts()}
        tool, R_world_tool = w.tool_pose()
        offset = w.object_position() - tool
        depth = float(offset @ R_world_tool[:, 2])
        evidence: dict[str, float | str | bool] = {
            "approval_to_grasp_s": a.t_grasp - self._started_at,
            "fingers_touching": len(touching & self._finger_names),
            "object_from_tool_m": float(np.linalg.norm(offset)),
            "object_in_jaw_m": depth, "jaw_opening_m": w.jaw_opening()}
        if touching >= self._finger_names and self._jaw_depth[0] <= depth <= self._jaw_depth[1]:
            return Result(a.plan_id, True, None, evidence)
        times = np.array([t for t, _ in self._truth])
        truth = np.array([p for _, p in self._truth])
        abrupt = self._abrupt_change(times, truth)
        if abrupt is not None:  # what went wrong after it, it caused
            return Result(a.plan_id, False, "abrupt_change", {**evidence, **abrupt})
        if self._touched:
            link, before = max(self._touched.items(), key=lambda kv: kv[1])
            return Result(a.plan_id, False, "collision",
                          {**evidence, "link": link, "before_grasp_s": before})
        reach = float(np.linalg.norm(self._tool_at_grasp - a.p_f))
        if reach > cfg.reach_tol_m:
            return Result(a.plan_id, False, "unreachable", {**evidence, "tool_from_p_f_m": reach})
        dist = np.linalg.norm(truth - a.p_f, axis=1)
        near = np.abs(times - a.t_grasp) <= cfg.timing_window_s
        at_grasp = float(np.interp(a.t_grasp, times, dist))
        evidence["object_from_p_f_at_grasp_m"] = at_grasp
        if at_grasp <= cfg.pass_tol_m:
            return Result(a.plan_id, False, "other", evidence)
        if np.any(near & (dist <= cfg.pass_tol_m)):
            t_pass = float(times[near][np.argmin(dist[near])])
            return Result(a.plan_id, False, "timing", {
                **evidence, "object_passed_s": t_pass - a.t_grasp,
                "arm": "early" if t_pass > a.t_grasp else "late"})
        return Result(a.plan_id, False, "prediction", evidence)

    def _abrupt_change(self, times: np.ndarray, truth: np.ndarray) -> dict | None:
        """Evidence that the object left the plan's prediction after the approval, or None."""
        a, limit = self.attempt, self.cfg.abrupt_m
        assert a is not None
        if a.predicted is None or a.approved_at is None:
            return None
        t_pred, p_pred = a.predicted
        window = (times >= a.approved_at) & (times <= min(a.t_grasp, t_pred[-1]))
        if not window.any():
            return None
        predicted = interpolate_path(t_pred, p_pred, times[window])
        off = np.linalg.norm(truth[window] - predicted, axis=1)
        if off[0] > limit / 2 or off.max() <= limit:
            return None
        return {"strayed_m": float(off.max()),
                "strayed_after_approval_s": float(times[window][np.argmax(off > limit)]
                                                  - a.approved_at)}

    def splice(self, update: Attempt, update_of: str) -> None:
        """Closed loop: from its first sample's time on, follow ``update``'s trajectory
        instead (the executing plan ``update_of`` moved to a newer prediction), towards its
        grasp point; raises ValueError if that plan is not the one executing."""
        a = self.attempt
        if a is None or a.plan_id != update_of:
            raise ValueError(f"update {update.plan_id}: plan {update_of} is not executing")
        keep = a.times < update.times[0] - 1e-9
        a.times = np.concatenate([a.times[keep], update.times])
        a.q, a.qd = np.vstack([a.q[keep], update.q]), np.vstack([a.qd[keep], update.qd])
        a.p_f, a.t_close, a.final_from = update.p_f, update.t_close, update.final_from
        if update.predicted is not None:  # judged against the prediction it follows now
            a.predicted, a.approved_at = update.predicted, self.world.time_s

    def abort(self, reason: str) -> Result:
        """Stop the attempt as the gate asked: open the jaw, back out along the approach
        and return to standby."""
        a = self.attempt
        assert a is not None
        return self._finish(Result(a.plan_id, False, None, {
            "reason": reason, "before_grasp_s": a.t_grasp - self.world.time_s,
            "approval_to_grasp_s": a.t_grasp - self._started_at}, aborted=True),
            back_m=self.cfg.retreat_m)

    def _finish(self, result: Result, back_m: float = 0.0) -> Result:
        """Open the jaw and head back to standby (ruckig, from the arm's state), first
        ``back_m`` metres back along the approach if that is reachable."""
        w, arm = self.world, self.world.arm
        standby = arm.q_home if self.attempt is None or self.attempt.standby is None else \
            np.clip(self.attempt.standby, arm.lower, arm.upper)
        self.attempt = None
        w.set_jaw(arm.jaw_max_opening_m)
        q, qd = w.arm_q()
        limits = Limits(arm.max_velocity, arm.max_acceleration, arm.max_jerk)
        zero = np.zeros(len(q))
        stops = [standby]
        if back_m > 0:
            T = arm.forward(q)
            T[:3, 3] -= back_m * T[:3, 2]
            q_back = arm.inverse(T, q)
            stops = [standby] if q_back is None else [q_back, standby]
        t, pieces = w.time_s, []
        for target in stops:
            move = segment(q, np.clip(qd, -limits.velocity, limits.velocity), zero, target,
                           zero, limits)
            if move is None:
                break
            piece = sample_segment(move, t, 0.02)
            pieces.append(tuple(x[1:] for x in piece) if pieces else piece)  # joined once
            t, q, qd = piece[0][-1], target, zero
        if pieces:
            self._return = tuple(np.concatenate(x) for x in zip(*pieces, strict=True))
        return result

    def go_to_standby(self, times: np.ndarray, q: np.ndarray, qd: np.ndarray) -> None:
        """Follow a timed move of the idle arm (times (k,) s, q and qd (k, n)), as after an
        attempt; raises ValueError while it executes or returns."""
        if self.busy:
            raise ValueError("the arm is executing or returning to standby")
        self._return = (times, q, qd)

    def _follow_return(self, t_s: float) -> None:
        if self._return is None:
            return
        times, q, qd = self._return
        if t_s >= times[-1]:
            self.world.command_arm(q[-1], np.zeros(q.shape[1]))
            self._return = None
            return
        k = int(np.searchsorted(times, t_s))
        self.world.command_arm(np.array([np.interp(t_s, times, q[:, j])
                                         for j in range(q.shape[1])]), qd[k])

"""Follow the arm's commanded paths in the simulated scene and judge each attempt physically.

The arm and the jaw follow the paths their controllers are sent (:meth:`Executor.follow`: a
joint trajectory controller's way, each new path replacing the rest from its first sample);
the judge knows of an attempt only from the approved plan (:meth:`Executor.start`), the
gate's abort and its updates, as an observer beside the tank would.

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

from wavegrasp.arm.motion import Attempt, JointPath
from wavegrasp.schemas.path import interpolate_path
from wavegrasp.sim.world import SimWorld

__all__ = ["Attempt", "Executor", "JudgeConfig", "Result"]


class JudgeConfig(BaseModel):
    settle_s: float = Field(0.6, description="after the grasp time, for the jaw to close")
    hold_s: float = Field(1.0, description="the object must stay held this long")
    reach_tol_m: float = 0.02
    pass_tol_m: float = 0.015
    timing_window_s: float = 0.5
    abrupt_m: float = 0.02


@dataclass
class Result:
    plan_id: str
    success: bool
    failure: str | None
    evidence: dict[str, float | str | bool] = field(default_factory=dict)
    aborted: bool = False


class Executor:
    """Follows the commanded paths in ``world`` and judges one attempt at a time;
    :meth:`advance` moves everything to a time."""

    def __init__(self, world: SimWorld, cfg: JudgeConfig | None = None) -> None:
        self.world, self.cfg = world, cfg or JudgeConfig()
        self.attempt: Attempt | None = None
        self.arm_path: JointPath | None = None
        self.jaw_path: JointPath | None = None
        self._jaw_target: np.ndarray | None = None
        self._at_end = False  # the arm was commanded its path's last point
        self._truth: list[tuple[float, np.ndarray]] = []
        self._touched: dict[str, float] = {}
        self._tool_at_grasp: np.ndarray | None = None
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
        """Judging an attempt or following a path."""
        return self.attempt is not None or self.moving

    @property
    def moving(self) -> bool:
        """Following a commanded path not at its end yet."""
        return self.arm_path is not None and self.world.time_s < self.arm_path.end_s

    @property
    def returning(self) -> bool:
        """Moving with no attempt judged: back to standby, or as the planner asked."""
        return self.attempt is None and self.moving

    def follow(self, path: JointPath) -> None:
        """Take a new path for the arm's joints or the jaw's (by its names), replacing the
        one followed from its first sample on; raises ValueError for other joints."""
        arm, now = self.world.arm, self.world.time_s
        if path.names == list(arm.joint_names):
            self.arm_path = path if self.arm_path is None else \
                self.arm_path.since(now).then(path)
            self._at_end = False
        elif path.names == list(arm.jaw_joints):
            self.jaw_path = path if self.jaw_path is None else \
                self.jaw_path.since(now).then(path)
            self._move_jaw()
        else:
            raise ValueError(f"joint names {path.names} are neither the arm's "
                             f"{list(arm.joint_names)} nor the jaw's {list(arm.jaw_joints)}")

    def hold(self) -> None:
        """Stop where the arm and the jaw are commanded to be now and hold there (the
        watchdog's stop: the link to the gate is gone)."""
        now = self.world.time_s
        if self.arm_path is not None:
            self.arm_path = JointPath.at_rest(self.arm_path.names, now, self.arm_path.at(now)[0])
            self._at_end = False
        if self.jaw_path is not None:
            self.jaw_path = JointPath.at_rest(self.jaw_path.names, now, self.jaw_path.at(now)[0])
        self._move_jaw()

    def _move_jaw(self) -> None:
        """Head the fingers where the jaw's path heads now (they move at their own speed)."""
        if self.jaw_path is None:
            return
        target = self.jaw_path.heading(self.world.time_s)
        if self._jaw_target is None or not np.array_equal(target, self._jaw_target):
            self.world.set_fingers(target)
            self._jaw_target = target

    def start(self, attempt: Attempt) -> None:
        """Judge ``attempt`` (the arm follows what its controller is sent)."""
        if self.attempt is not None:
            raise ValueError(f"plan {attempt.plan_id}: {self.attempt.plan_id} is judged")
        self.attempt = attempt
        self._started_at = self.world.time_s  # approved (updates do not move it)
        self._truth, self._touched = [], {}
        self._tool_at_grasp = None
        self.world.tether_touches()  # those on the way back from the last attempt are not its

    def advance(self, t_s: float, position: np.ndarray, quat_xyzw: np.ndarray) -> Result | None:
        """Drive the object to its pose at ``t_s``, the arm along its path, step the world to
        ``t_s``; returns the attempt's result once it is judged."""
        w = self.world
        w.drive_object(position, quat_xyzw)
        a = self.attempt
        w.watch_tether = a is not None and w.time_s < a.t_grasp  # read below only then
        if self.arm_path is not None and not self._at_end:  # at its end it holds there
            w.command_arm(*self.arm_path.at(t_s))
            self._at_end = t_s >= self.arm_path.end_s
        w.step_to(t_s)
        result = None if a is None else self._watch(a, t_s, position)
        self._move_jaw()  # after the judging: the jaw opens once the grasp was held
        return result

    def _watch(self, a: Attempt, t_s: float, position: np.ndarray) -> Result | None:
        w = self.world
        self._truth.append((t_s, position.copy()))
        if w.time_s < a.t_grasp:
            for link in w.contacts():
                name = self._names[link]
                if name in self._finger_names and w.time_s >= a.final_from:
                    continue  # the object entering the jaw in the final move
                self._touched.setdefault(name, a.t_grasp - w.time_s)
            for link in w.tether_touches():
                self._touched.setdefault(f"{self._names[link]} on the tether",
                                         a.t_grasp - w.time_s)
        if self._tool_at_grasp is None and w.time_s >= a.t_grasp:
            self._tool_at_grasp = w.tool_position()
        if w.time_s >= a.t_grasp + self.cfg.settle_s + self.cfg.hold_s:
            result, self.attempt = self._judge(), None
            return result
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
        """Closed loop: judge the executing plan ``update_of`` by ``update`` from now on (its
        grasp point, times and prediction; the arm follows the update's path as sent); raises
        ValueError if that plan is not the one executing."""
        a = self.attempt
        if a is None or a.plan_id != update_of:
            raise ValueError(f"update {update.plan_id}: plan {update_of} is not executing")
        a.p_f, a.t_close, a.final_from = update.p_f, update.t_close, update.final_from
        if update.predicted is not None:  # judged against the prediction it follows now
            a.predicted, a.approved_at = update.predicted, self.world.time_s

    def abort(self, reason: str) -> Result:
        """The gate stopped the attempt (the arm backs out as its commander sends it)."""
        a = self.attempt
        assert a is not None
        self.attempt = None
        return Result(a.plan_id, False, None, {
            "reason": reason, "before_grasp_s": a.t_grasp - self.world.time_s,
            "approval_to_grasp_s": a.t_grasp - self._started_at}, aborted=True)

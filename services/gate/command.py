"""The arm's commander: what the gate approves, turned into the paths a ros2_control arm follows.

Every motion of the arm is a :class:`~wavegrasp.arm.motion.JointPath` for its joint
trajectory controller and one for the jaw's: an approved plan (its samples, then holding the
grasp ``hold_s`` after the grasp time, then back to standby with the jaw open), a closed-loop
update (from its first sample on, replacing the rest), an abort (from the commanded state
now: back ``retreat_m`` along the approach, then to standby, the jaw opened at once) and the
planner's standby moves (only while nothing else is commanded). No bus here: the gate service
sends what this returns. Times are seconds on the recording clock.
"""

from __future__ import annotations

import numpy as np
from pydantic import BaseModel, Field

from wavegrasp.arm import ArmModel
from wavegrasp.arm.motion import Attempt, JointPath
from wavegrasp.planner.timing import Limits, sample_segment, segment

#: The gap (s) between two jaw samples that would otherwise share a time.
JAW_GAP_S = 1e-3


class CommandConfig(BaseModel):
    hold_s: float = Field(1.6, gt=0, description="the arm holds a grasp this long after the "
                          "grasp time, then opens the jaw and returns to standby")
    retreat_m: float = Field(0.08, ge=0, description="an aborted attempt backs the tool out "
                             "this far along its approach before it returns to standby")
    closed_m: float = Field(0.0, ge=0, description="the jaw's commanded opening when closing")
    sample_s: float = Field(0.02, gt=0, description="the time between samples of a return "
                            "or a retreat")
    heartbeat_s: float = Field(0.1, gt=0, description="wall seconds between the gate's "
                               "heartbeats, which the arm's watchdog waits for")


class Commander:
    """Keeps the arm's commanded path (:attr:`arm_path`) and makes each new one."""

    def __init__(self, arm: ArmModel, config: CommandConfig | None = None) -> None:
        self.arm, self.cfg = arm, config or CommandConfig()
        self.names = list(arm.joint_names)
        self.jaw_names = list(arm.jaw_joints)
        self.arm_path: JointPath | None = None
        self.jaw_path: JointPath | None = None
        self.standby_q: np.ndarray | None = None  # the last plan's standby (None: home)
        self._limits = Limits(arm.max_velocity, arm.max_acceleration, arm.max_jerk)

    def busy(self, now_s: float) -> bool:
        """Is a commanded path still under way at ``now_s``?"""
        return self.arm_path is not None and now_s < self.arm_path.end_s

    def grasp(self, attempt: Attempt, update: bool = False, now_s: float | None = None
              ) -> tuple[JointPath, JointPath]:
        """An approved plan (``update``: a closed-loop update of the one commanded) at
        ``now_s`` (default: its first sample's time): the arm's path and the jaw's,
        replacing what was commanded from the plan's first sample on. A jaw already narrowed
        or closing is not opened again by an update."""
        plan = attempt.path(self.names)
        if not update:  # an update's return goes where its plan's went
            self.standby_q = attempt.standby
        t0, t_end = plan.times[0], max(attempt.t_grasp + self.cfg.hold_s, plan.end_s)
        if t_end > plan.end_s:  # hold the grasp
            plan = plan.then(JointPath.at_rest(self.names, t_end, plan.q[-1]))
        back = self.back_to_standby(plan.q[-1], np.zeros(len(self.names)), t_end,
                                    self.standby_q)
        path = plan.then(back) if back is not None else plan
        wide, closed = self.arm.jaw_max_opening_m, self.cfg.closed_m
        now = wide if not update or self.jaw_path is None else \
            float(np.sum(self.jaw_path.heading(t0)))
        events = [(t0, now)]
        if attempt.jaw_preshape_m > 0 and t0 <= attempt.final_from < attempt.t_close \
                and now >= wide - 1e-6:
            events.append((attempt.final_from, attempt.jaw_preshape_m))
        if now > closed + 1e-6:
            events.append((max(attempt.t_close, t0), closed))
        events.append((t_end, wide))
        return self._command(path, self.jaw(events), t0 if now_s is None else now_s)

    def abort(self, now_s: float) -> tuple[JointPath, JointPath] | None:
        """Stop what is commanded now: back out along the approach and return to standby,
        the jaw opened at once; None if nothing is commanded."""
        if self.arm_path is None:
            return None
        q, qd = self.arm_path.at(now_s)
        back = self.back_to_standby(q, qd, now_s, self.standby_q, self.cfg.retreat_m)
        if back is None:  # no move found: hold where it is
            back = JointPath.at_rest(self.names, now_s, q)
        return self._command(back, self.jaw([(now_s, self.arm.jaw_max_opening_m)]), now_s)

    def standby(self, move: JointPath, now_s: float) -> JointPath | None:
        """The planner's move of the idle arm, or None while another path is under way."""
        if move.names != self.names:
            raise ValueError(f"standby joint_names {move.names} are not the arm's {self.names}")
        if self.busy(now_s):
            return None
        return self._command(move, None, now_s)[0]

    def _command(self, path: JointPath, jaw: JointPath | None, now_s: float
                 ) -> tuple[JointPath, JointPath | None]:
        """Keep what is commanded from ``now_s`` on (as the controllers follow it)."""
        self.arm_path = path if self.arm_path is None else \
            self.arm_path.since(now_s).then(path)
        if jaw is not None:
            self.jaw_path = jaw if self.jaw_path is None else \
                self.jaw_path.since(now_s).then(jaw)
        return path, jaw

    def jaw(self, events: list[tuple[float, float]]) -> JointPath:
        """The jaw's path through (time s, opening m) events: each opening held until the
        next event, then reached at the jaw's speed. Positions per finger joint."""
        speed = max(self.arm.jaw_closing_mps, 1e-3)
        times, openings = [events[0][0]], [events[0][1]]
        for t, opening in events[1:]:
            if t > times[-1] + JAW_GAP_S and opening != openings[-1]:
                times.append(t)
                openings.append(openings[-1])
            move = abs(opening - openings[-1]) / speed
            times.append(max(t + move, times[-1] + JAW_GAP_S))
            openings.append(opening)
        return JointPath(self.jaw_names, times, [self.fingers(o) for o in openings],
                         np.zeros((len(times), len(self.jaw_names))))

    def fingers(self, opening_m: float) -> np.ndarray:
        """Each finger joint's position for a gap of ``opening_m``, within its limits."""
        lim = [self.arm.joints[name] for name in self.jaw_names]
        share = opening_m / max(len(lim), 1)
        return np.array([np.clip(share, j.lower, j.upper) for j in lim])

    def back_to_standby(self, q: np.ndarray, qd: np.ndarray, t_s: float,
                        standby: np.ndarray | None, back_m: float = 0.0) -> JointPath | None:
        """From (q, qd) at ``t_s`` to standby (its home pose if None) at rest, first
        ``back_m`` back along the tool's approach if that is reachable (ruckig,
        time-optimal); None if no move is found."""
        arm, limits = self.arm, self._limits
        target = arm.q_home if standby is None else np.clip(standby, arm.lower, arm.upper)
        stops = [target]
        if back_m > 0:
            T = arm.forward(q)
            T[:3, 3] -= back_m * T[:3, 2]
            q_back = arm.inverse(T, q)
            stops = [target] if q_back is None else [q_back, target]
        zero, pieces = np.zeros(len(q)), []
        for stop in stops:
            move = segment(q, np.clip(qd, -limits.velocity, limits.velocity), zero, stop, zero,
                           limits)
            if move is None:
                break
            piece = sample_segment(move, t_s, self.cfg.sample_s)
            pieces.append(tuple(x[1:] for x in piece) if pieces else piece)  # joined once
            t_s, q, qd = piece[0][-1], stop, zero
        if not pieces:
            return None
        times, qs, qds = (np.concatenate(x) for x in zip(*pieces, strict=True))
        return JointPath(self.names, times, qs, qds)

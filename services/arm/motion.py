"""What the arm is told to do: timed joint paths and the approved plans they come from.

A :class:`JointPath` is what a ``trajectory_msgs/msg/JointTrajectory`` carries to a
ros2_control joint trajectory controller (the commander sends them, the sim or a real arm
follows them); an :class:`Attempt` is an approved grasp plan as the commander and the judge
read it. Times are seconds on the recording clock (a live vehicle's clock is the wall).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from wavegrasp.schemas import GraspPlan


def check_path(times: np.ndarray, q: np.ndarray, qd: np.ndarray, names: list[str]) -> None:
    """Raise ValueError naming what is wrong with a timed path of ``len(names)`` joints."""
    n = len(names)
    if times.ndim != 1 or len(times) < 1:
        raise ValueError(f"times must have shape (k,) with k >= 1, got {times.shape}")
    if q.shape != (len(times), n) or qd.shape != (len(times), n):
        raise ValueError(f"positions and velocities must have shape ({len(times)}, {n}), got "
                         f"{q.shape} and {qd.shape}")
    if not (np.isfinite(times).all() and np.isfinite(q).all() and np.isfinite(qd).all()):
        raise ValueError("times, positions and velocities must be finite")
    if np.any(np.diff(times) <= 0):
        raise ValueError("times must increase strictly")


@dataclass
class JointPath:
    """A timed path of named joints.

    names : list of n joint names; times : array, shape (k,), s; q : array, shape (k, n),
    rad (revolute) or m (prismatic); qd : array, shape (k, n), their rates.
    """

    names: list[str]
    times: np.ndarray
    q: np.ndarray
    qd: np.ndarray

    def __post_init__(self) -> None:
        self.times = np.asarray(self.times, dtype=float)
        self.q = np.asarray(self.q, dtype=float).reshape(len(self.times), -1)
        self.qd = np.asarray(self.qd, dtype=float).reshape(len(self.times), -1)
        check_path(self.times, self.q, self.qd, self.names)

    @classmethod
    def at_rest(cls, names: list[str], t_s: float, q: np.ndarray) -> JointPath:
        """One point: positions ``q`` (n,) held from ``t_s`` on."""
        return cls(names, [t_s], [q], [np.zeros(len(q))])

    @property
    def end_s(self) -> float:
        return float(self.times[-1])

    def at(self, t_s: float) -> tuple[np.ndarray, np.ndarray]:
        """Positions (n,) interpolated at ``t_s`` (the first before the path, the last
        after it) and the velocities (n,) of the sample ending the span ``t_s`` is in (zero
        outside the path): a position controller's target with its feed-forward."""
        times, still = self.times, np.zeros(self.q.shape[1])
        if t_s >= times[-1]:
            return self.q[-1].copy(), still
        if t_s <= times[0]:
            return self.q[0].copy(), (self.qd[0] if t_s == times[0] else still)
        k = int(np.searchsorted(times, t_s))
        w = (t_s - times[k - 1]) / (times[k] - times[k - 1])
        return self.q[k - 1] + (self.q[k] - self.q[k - 1]) * w, self.qd[k]

    def heading(self, t_s: float) -> np.ndarray:
        """Positions (n,) of the sample ending the span ``t_s`` is in (the first before the
        path, the last after it): where a joint driven at its own speed limit heads, as a jaw
        is."""
        k = int(np.searchsorted(self.times, t_s, side="right"))
        return self.q[min(k, len(self.times) - 1)]

    def since(self, t_s: float) -> JointPath:
        """The path from its last sample at or before ``t_s`` on: the same from ``t_s``, and
        followed paths do not grow without end."""
        k = max(int(np.searchsorted(self.times, t_s, side="right")) - 1, 0)
        return self if k == 0 else JointPath(self.names, self.times[k:], self.q[k:], self.qd[k:])

    def then(self, later: JointPath) -> JointPath:
        """This path up to ``later``'s first sample, then ``later``: how a joint trajectory
        controller takes a new trajectory while following one."""
        if later.names != self.names:
            raise ValueError(f"joint names {later.names} are not the path's {self.names}")
        keep = self.times < later.times[0] - 1e-9
        return JointPath(self.names, np.concatenate([self.times[keep], later.times]),
                         np.vstack([self.q[keep], later.q]),
                         np.vstack([self.qd[keep], later.qd]))


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

    def path(self, names: list[str]) -> JointPath:
        """The plan's own samples as a path of the arm's joints ``names``."""
        return JointPath(list(names), self.times, self.q, self.qd)

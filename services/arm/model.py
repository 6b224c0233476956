"""The arm's kinematic model, read from a URDF: limits, forward and inverse kinematics."""

from __future__ import annotations

import importlib.resources
import math
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from wavegrasp.arm import ik
from wavegrasp.arm.kinematics import Chain
from wavegrasp.arm.limits import Joint, apply_overrides, joint_limits
from wavegrasp.arm.urdf import DEFAULT_RADIUS, UrdfRobot, parse_urdf
from wavegrasp.checks import check_transform, check_unit, check_vector

__all__ = ["ArmModel", "Joint", "DEFAULT_URDF"]

#: File name of the packaged Bravo-7-like model.
DEFAULT_URDF = "bravo7_like.urdf"
#: Restarts after the seed and home pose: fixed joint vectors drawn within the limits.
N_RESTARTS = 16


class ArmModel:
    """A serial arm from `base_link` to `tool_link` and its jaw, from a URDF.

    `q` is one value per arm joint, in `joint_names` order: array, shape (n,), radians
    (n = 6 for a Bravo-7-class arm). Poses are in frame `base_link`, metres.
    Use :meth:`load`; attributes: `joint_names`, `joints` (name -> :class:`Joint`, the arm
    joints then the jaw joints), `jaw_joints`, `jaw_max_opening_m`, `base_link`, `tool_link`,
    `link_names` (the chain's links after the base, the order of :meth:`forward_all`),
    `reach_m` (shoulder to tool with the arm straight: the offsets after the second arm joint),
    `q_home`, `hand_capsules` (p0, p1 : arrays, shape (h, 3), metres, frame tool; radius :
    shape (h,): the links after the last arm joint, jaw fingers excluded), `jaw_capsules` (the
    same for the fingers, the jaw fully open), and `lower`,
    `upper`, `max_velocity`, `max_acceleration`, `max_jerk` (arrays,
    shape (n,), over the arm joints).
    """

    def __init__(self, robot: UrdfRobot, tool_link: str, base_link: str | None,
                 overrides: dict[str, dict[str, float]] | None) -> None:
        self.urdf_path: Path | None = None  # the file it was read from (the sim loads it)
        self.base_link = base_link or robot.root()
        self.tool_link = tool_link
        self._chain = Chain(robot.chain(self.base_link, tool_link))
        self.link_names = [j.child for j in self._chain.joints]
        self.joint_names = [j.name for j in self._chain.movable]
        if not self.joint_names:
            raise ValueError(f"no movable joints between {self.base_link!r} and {tool_link!r}")
        on_chain = {self.base_link, *self.link_names}
        self.jaw_joints = robot.jaw_joints if robot.jaw_joints is not None else [
            j.name for j in robot.joints.values()
            if j.type == "prismatic" and j.parent in on_chain and j.child not in on_chain]
        #: The jaw's fingers' URDF joints (their origins and axes: a viewer draws them).
        self.jaw = [robot.joints[name] for name in self.jaw_joints]
        joints = {j.name: joint_limits(j, robot.extra_limits.get(j.name, {}))
                  for j in [*self._chain.movable, *self.jaw]}
        self.joints = apply_overrides(joints, overrides)
        self.jaw_max_opening_m = robot.jaw_max_opening if robot.jaw_max_opening is not None \
            else sum(self.joints[n].upper - self.joints[n].lower for n in self.jaw_joints)
        #: How fast the jaw's gap closes, m/s: every finger at its speed limit.
        self.jaw_closing_mps = sum(self.joints[n].max_velocity for n in self.jaw_joints) or 0.1
        arm = [self.joints[n] for n in self.joint_names]
        self.lower = np.array([j.lower for j in arm])
        self.upper = np.array([j.upper for j in arm])
        self.max_velocity = np.array([j.max_velocity for j in arm])
        self.max_acceleration = np.array([j.max_acceleration for j in arm])
        self.max_jerk = np.array([j.max_jerk for j in arm])
        n = len(arm)
        if robot.home is not None and robot.home.shape != (n,):
            raise ValueError(f"<home q> has {robot.home.size} values, the arm {n} joints")
        home = robot.home if robot.home is not None else np.zeros(n)
        self.q_home = np.clip(home, self.lower, self.upper)
        self.reach_m = self._chain.reach_after(min(1, n - 1))
        self._reach_bound = self._chain.reach_after(0)
        self._wrist_turns_over = ik.wrist_turns_over(self._chain, self.lower, self.upper)
        #: The first joint's origin, array, shape (3,), metres, frame base_link (it never moves).
        self.shoulder = self._chain.frames(self.q_home)[1][0]
        rng = np.random.default_rng(0)
        self._restarts = list(rng.uniform(self.lower, self.upper, (N_RESTARTS, n)))
        self._shapes = robot.links
        self._jaw_parent = [self.link_names.index(j.parent) if j.parent in self.link_names
                            else -1 for j in self.jaw]
        self._capsule_layout()

    @classmethod
    def load(cls, path: str | Path | None = None,
             overrides: dict[str, dict[str, float]] | None = None, *,
             tool_link: str = "tool", base_link: str | None = None) -> ArmModel:
        """Read an arm from the URDF at `path`, by default wavegrasp's Bravo-7-like model.

        overrides : per-joint limits replacing the URDF's, e.g.
            {"wrist_roll": {"max_velocity": 0.5}}; fields are those of :class:`Joint`.
        tool_link, base_link : the chain's ends; base_link defaults to the URDF's root link.
        A URDF without wavegrasp's <limits> elements gets :data:`limits.DEFAULTS`.
        """
        if path is None:
            with importlib.resources.as_file(
                    importlib.resources.files("wavegrasp.arm") / DEFAULT_URDF) as p:
                arm = cls(parse_urdf(p), tool_link, base_link, overrides)
                arm.urdf_path = Path(p)
                return arm
        if not Path(path).is_file():
            raise ValueError(f"arm URDF {str(path)!r} does not exist")
        arm = cls(parse_urdf(path), tool_link, base_link, overrides)
        arm.urdf_path = Path(path)
        return arm

    # --- limits ---------------------------------------------------------------------------

    def check_q(self, q: np.ndarray) -> np.ndarray:
        """Return q as array, shape (n,), radians; raise ValueError naming the first joint
        outside its limits (or a wrong shape or non-finite value)."""
        q = check_vector("q", q, len(self.joint_names))
        for name, value, lo, hi in zip(self.joint_names, q, self.lower, self.upper, strict=True):
            if not lo - 1e-9 <= value <= hi + 1e-9:
                raise ValueError(f"q: joint {name!r} = {value:.6g} outside [{lo:.6g}, {hi:.6g}]")
        return q

    def within_limits(self, q: np.ndarray) -> bool:
        """Whether q (array, shape (n,), radians) is finite and within every joint's limits."""
        try:
            self.check_q(q)
        except ValueError:
            return False
        return True

    # --- forward kinematics ---------------------------------------------------------------

    def forward(self, q: np.ndarray) -> np.ndarray:
        """T_base_tool : array, shape (4, 4), frame base_link, of q (array, shape (n,),
        radians)."""
        return self._chain.frames(check_vector("q", q, len(self.joint_names)))[0]

    def forward_batch(self, q: np.ndarray) -> np.ndarray:
        """T_base_tool at m configurations q (array, shape (m, n), radians): array, shape
        (m, 4, 4), frame base_link."""
        return self._chain.forward_batch(np.asarray(q, dtype=float))[:, -1]

    def forward_all(self, q: np.ndarray) -> list[np.ndarray]:
        """T_base_link for each link in `link_names`: arrays, shape (4, 4), frame base_link."""
        return self._chain.forward_all(check_vector("q", q, len(self.joint_names)))

    def jacobian(self, q: np.ndarray) -> np.ndarray:
        """Geometric Jacobian, array, shape (6, n): rows 0-2 the tool origin's velocity (m/s),
        rows 3-5 its angular velocity (rad/s), both in frame base_link, per rad/s of each
        joint."""
        return self._chain.jacobian(check_vector("q", q, len(self.joint_names)))

    def link_capsules(self, q: np.ndarray, jaw_opening_m: float | None = None
                      ) -> list[tuple[np.ndarray, np.ndarray, float]]:
        """Capsules (p0, p1 : arrays, shape (3,), metres, frame base_link; radius, metres)
        around the moving links' collision shapes, jaw fingers included at `jaw_opening_m`
        (default fully open), the jaw's last (`jaw_capsule_count` of them). A moving link
        without usable shapes (a mesh) gets a capsule of radius DEFAULT_RADIUS from its
        origin to the next link's."""
        p0, p1, radius = self.capsules_batch(
            check_vector("q", q, len(self.joint_names))[None], jaw_opening_m)
        return [(a, b, float(r)) for a, b, r in zip(p0[0], p1[0], radius, strict=True)]

    def capsules_batch(self, q: np.ndarray, jaw_opening_m: float | None = None
                       ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """:meth:`link_capsules` at m configurations q (array, shape (m, n), radians):
        p0, p1 : arrays, shape (m, c, 3), metres, frame base_link; radius : shape (c,)."""
        chain = self._chain.forward_batch(np.asarray(q, dtype=float))
        frames = np.concatenate([chain, np.repeat(chain[:, :1], len(self.jaw), axis=1)], axis=1)
        opening = self.jaw_max_opening_m if jaw_opening_m is None else jaw_opening_m
        for joint, parent, k in zip(self.jaw, self._jaw_parent, self._jaw_frame, strict=True):
            if parent < 0:
                continue
            lim = self.joints[joint.name]
            M = joint.origin.copy()
            M[:3, 3] += M[:3, :3] @ (np.clip(opening / len(self.jaw), lim.lower, lim.upper)
                                     * joint.axis)
            frames[:, k] = frames[:, parent] @ M
        T = frames[:, self._capsule_frame]
        p0 = np.einsum("mcij,cj->mci", T[..., :3, :3], self._capsule_p0) + T[..., :3, 3]
        p1 = np.einsum("mcij,cj->mci", T[..., :3, :3], self._capsule_p1) + T[..., :3, 3]
        for c, k in self._capsule_to_next:  # links without shapes: origin to the next link's
            p1[:, c] = frames[:, k + 1, :3, 3]
        return p0, p1, self._capsule_radius

    def _capsule_layout(self) -> None:
        """Which frame each capsule hangs on and its ends there, for :meth:`capsules_batch`;
        the jaw fingers' frames are appended after the chain's."""
        n_links = len(self.link_names)
        self._jaw_frame = [n_links + i for i in range(len(self.jaw))]
        frame, p0, p1, radius, to_next = [], [], [], [], []
        moved = {j.child for j in self._chain.movable}
        for k, name in enumerate(self.link_names):
            shapes = self._shapes.get(name, [])
            if not shapes and name in moved and k + 1 < n_links:
                to_next.append((len(frame), k))
                frame.append(k)
                p0.append(np.zeros(3))
                p1.append(np.zeros(3))
                radius.append(DEFAULT_RADIUS)
            for c in shapes:
                frame.append(k)
                p0.append(c.p0)
                p1.append(c.p1)
                radius.append(c.radius)
        self.jaw_capsule_count = 0
        for joint, parent, k in zip(self.jaw, self._jaw_parent, self._jaw_frame, strict=True):
            if parent < 0:
                continue
            for c in self._shapes.get(joint.child, []):
                self.jaw_capsule_count += 1
                frame.append(k)
                p0.append(c.p0)
                p1.append(c.p1)
                radius.append(c.radius)
        self._capsule_frame = np.array(frame, dtype=int)
        self._capsule_p0, self._capsule_p1 = np.array(p0), np.array(p1)
        self._capsule_radius = np.array(radius)
        self._capsule_to_next = to_next
        # The hand: capsules on links after the last arm joint, fixed in the tool frame.
        last = max(k for k, j in enumerate(self._chain.joints) if j.movable)
        hand = (self._capsule_frame >= last) & (self._capsule_frame < n_links)
        p0, p1, r = self.capsules_batch(self.q_home[None])
        T_tool_base = np.linalg.inv(self.forward(self.q_home))
        def to_tool(p: np.ndarray, which: np.ndarray) -> np.ndarray:
            return p[0, which] @ T_tool_base[:3, :3].T + T_tool_base[:3, 3]

        self.hand_capsules = (to_tool(p0, hand), to_tool(p1, hand), r[hand])
        jaw = np.arange(len(r)) >= len(r) - self.jaw_capsule_count
        self.jaw_capsules = (to_tool(p0, jaw), to_tool(p1, jaw), r[jaw])

    # --- inverse kinematics ---------------------------------------------------------------

    def _seeds(self, q_seed: np.ndarray, restarts: int | None = None,
               target: np.ndarray | None = None) -> Iterator[np.ndarray]:
        # Lazily: the facing pose costs a forward kinematics pass, and the seed alone
        # usually converges.
        yield q_seed
        if restarts == -1:
            return
        if target is not None:
            yield self.facing(target)
        yield self.q_home
        yield from self._restarts[:restarts]

    def facing(self, p: np.ndarray) -> np.ndarray:
        """The home pose with the first joint turned so the arm faces ``p`` (array, shape
        (3,), metres, frame base_link): array, shape (n,), radians, within limits. An arm
        mounted at any yaw then starts its search on the object's side."""
        q = self.q_home.copy()
        if self._chain.movable[0].type == "prismatic":
            return q
        T, P, Z = self._chain.frames(q)
        axis = Z[0]
        flat = [v - (v @ axis) * axis for v in (T[:3, 3] - P[0], np.asarray(p) - P[0])]
        if min(np.linalg.norm(v) for v in flat) < 1e-6:
            return q
        angle = math.atan2(float(axis @ np.cross(flat[0], flat[1])), float(flat[0] @ flat[1]))
        q[0] = np.clip(q[0] + angle, self.lower[0], self.upper[0])
        return q

    def _out_of_reach(self, p: np.ndarray, position_tol: float) -> bool:
        return float(np.linalg.norm(p - self.shoulder)) > self._reach_bound + position_tol

    def inverse(self, T_target: np.ndarray, q_seed: np.ndarray, position_tol: float = 1e-3,
                angle_tol_deg: float = 2.0, max_iter: int = 100,
                restarts: int | None = None) -> np.ndarray | None:
        """q (array, shape (n,), radians, within limits) with forward(q) within position_tol
        metres and angle_tol_deg degrees of T_target (array, shape (4, 4), frame base_link),
        or None if unreachable. Tries q_seed (array, shape (n,), radians) first, then the
        home pose turned to face the target (:meth:`facing`), the home pose and fixed restarts
        (all, or the first ``restarts``; -1: q_seed alone; max_iter iterations each);
        deterministic."""
        T_target = check_transform("T_target", T_target)
        q_seed = np.clip(check_vector("q_seed", q_seed, len(self.joint_names)),
                         self.lower, self.upper)
        if self._out_of_reach(T_target[:3, 3], position_tol):
            return None
        return ik.solve(self._chain, self.lower, self.upper,
                        self._seeds(q_seed, restarts, T_target[:3, 3]), T_target[:3, 3],
                        R_target=T_target[:3, :3], position_tol=position_tol,
                        angle_tol=np.radians(angle_tol_deg), max_iter=max_iter)

    def wrist_twins(self, q: np.ndarray) -> list[np.ndarray]:
        """q (radians, shape (n,)) and the other joint values, within limits, that hold the
        tool exactly as q does with the wrist turned over (:func:`ik.wrist_twins`); q alone
        for an arm whose wrist does not turn over so."""
        q = self.check_q(q)
        if not self._wrist_turns_over:
            return [q]
        return ik.wrist_twins(self.lower, self.upper, q)

    def inverse_position(self, p: np.ndarray, approach: np.ndarray, q_seed: np.ndarray,
                         position_tol: float = 1e-3, angle_tol_deg: float = 2.0,
                         max_iter: int = 100) -> tuple[np.ndarray, np.ndarray] | None:
        """A grasp at p (array, shape (3,), metres, frame base_link) with the tool's z axis
        along `approach` (array, shape (3,), unit, frame base_link), rotation about it free:
        (q, T_base_tool) or None. The jaw direction comes out near q_seed's; for a symmetric
        jaw, of the wrist-roll values pi apart the one closest to q_seed is chosen."""
        p = check_vector("p", p, 3)
        approach = check_unit("approach", approach)
        q_seed = np.clip(check_vector("q_seed", q_seed, len(self.joint_names)),
                         self.lower, self.upper)
        if self._out_of_reach(p, position_tol):
            return None
        q = ik.solve(self._chain, self.lower, self.upper, self._seeds(q_seed, target=p), p,
                     approach=approach, position_tol=position_tol,
                     angle_tol=np.radians(angle_tol_deg), max_iter=max_iter)
        if q is None:
            return None
        q = ik.flip_last_roll(self._chain, self.lower, self.upper, q, q_seed)
        return q, self.forward(q)

"""Forward kinematics and the geometric Jacobian of a serial chain of URDF joints."""

from __future__ import annotations

import math

import numpy as np

from wavegrasp.arm.transforms import cross, skew
from wavegrasp.arm.urdf import UrdfJoint


class Chain:
    """The joints from a base link to a tip link; `q` holds one value per movable joint
    (radians for revolute joints, metres for prismatic ones), in chain order."""

    def __init__(self, joints: list[UrdfJoint]) -> None:
        self.joints = joints
        self.movable = [j for j in joints if j.movable]
        self._K = [skew(j.axis) for j in joints]
        self._K2 = [K @ K for K in self._K]
        self._prismatic = np.array([j.type == "prismatic" for j in self.movable])
        self._any_prismatic = bool(self._prismatic.any())
        # Per joint: its origin's rotation and offset, and which entry of q moves it (-1: fixed).
        self._R0 = [j.origin[:3, :3].copy() for j in joints]
        # Most joint origins do not rotate: R @ I is R, so `frames` skips that product.
        self._rotates = [not np.array_equal(R0, np.eye(3)) for R0 in self._R0]
        self._p0 = [j.origin[:3, 3].copy() for j in joints]
        index = np.cumsum([j.movable for j in joints]) - 1
        self._q_index = [int(i) if j.movable else -1 for i, j in zip(index, joints, strict=True)]

    @property
    def dof(self) -> int:
        return len(self.movable)

    def forward_batch(self, q: np.ndarray) -> np.ndarray:
        """T_base_link for each joint's child link at each of m configurations: q : array,
        shape (m, n); returns array, shape (m, len(joints), 4, 4), frame base."""
        m = len(q)
        out = np.zeros((m, len(self.joints), 4, 4))
        out[:, :, 3, 3] = 1.0
        R, p = np.broadcast_to(np.eye(3), (m, 3, 3)), np.zeros((m, 3))
        for k, joint in enumerate(self.joints):
            p = p + R @ self._p0[k]
            R = R @ self._R0[k]
            i = self._q_index[k]
            if i >= 0 and joint.type == "prismatic":
                p = p + q[:, i, None] * (R @ joint.axis)
            elif i >= 0:
                s, c = np.sin(q[:, i])[:, None, None], np.cos(q[:, i])[:, None, None]
                R = R + R @ (s * self._K[k] + (1.0 - c) * self._K2[k])
            out[:, k, :3, :3], out[:, k, :3, 3] = R, p
        return out

    def forward_all(self, q: np.ndarray) -> list[np.ndarray]:
        """T_base_link for each joint's child link, arrays, shape (4, 4), frame base."""
        return list(self.forward_batch(np.asarray(q, dtype=float)[None])[0])

    def frames(self, q: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """T_base_tip, array, shape (4, 4); each movable joint's origin, array, shape (n, 3),
        metres, and unit axis, array, shape (n, 3); all in frame base."""
        n = self.dof
        P, Z = np.empty((n, 3)), np.empty((n, 3))
        R, p = np.eye(3), np.zeros(3)
        values = np.asarray(q, dtype=float).tolist()  # Python floats: cheaper in math.sin
        for k, joint in enumerate(self.joints):
            p = p + R @ self._p0[k]
            if self._rotates[k]:
                R = R @ self._R0[k]
            i = self._q_index[k]
            if i < 0:
                continue
            P[i] = p
            Z[i] = R @ joint.axis
            if joint.type == "prismatic":
                p = p + values[i] * Z[i]
            else:
                R = R + R @ (math.sin(values[i]) * self._K[k]
                             + (1.0 - math.cos(values[i])) * self._K2[k])
        T = np.eye(4)
        T[:3, :3], T[:3, 3] = R, p
        return T, P, Z

    def jacobian_at(self, T: np.ndarray, P: np.ndarray, Z: np.ndarray) -> np.ndarray:
        """Geometric Jacobian, shape (6, n): rows linear (m per unit q) then angular velocity
        (rad/s per unit q) of the tip, both in frame base, from the output of `frames`."""
        J = np.empty((6, self.dof))
        if not self._any_prismatic:  # the usual arm: no need to pick per joint
            J[:3] = cross(Z, T[:3, 3] - P).T
            J[3:] = Z.T
            return J
        J[:3] = np.where(self._prismatic[:, None], Z, cross(Z, T[:3, 3] - P)).T
        J[3:] = np.where(self._prismatic[:, None], 0.0, Z).T
        return J

    def jacobian(self, q: np.ndarray) -> np.ndarray:
        """Geometric Jacobian, shape (6, n), frame base (see `jacobian_at`)."""
        return self.jacobian_at(*self.frames(q))

    def reach_after(self, i: int) -> float:
        """Upper bound (m) on the distance from movable joint i's origin to the tip: the sum
        of the later joints' offsets and prismatic travels."""
        k = self.joints.index(self.movable[i])
        total = 0.0
        for joint in self.joints[k + 1:]:
            total += float(np.linalg.norm(joint.origin[:3, 3]))
            if joint.type == "prismatic":
                total += max(abs(joint.lower), abs(joint.upper))
        if self.joints[k].type == "prismatic":
            total += max(abs(self.joints[k].lower), abs(self.joints[k].upper))
        return total

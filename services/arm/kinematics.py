"""Forward kinematics and the geometric Jacobian of a serial chain of URDF joints."""

from __future__ import annotations

import math

import numpy as np

from wavegrasp.arm.transforms import skew
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

    @property
    def dof(self) -> int:
        return len(self.movable)

    def _motion(self, k: int, value: float) -> np.ndarray:
        """Transform, shape (4, 4), of joint k (index into `joints`) moved by `value`."""
        M = np.eye(4)
        if self.joints[k].type == "prismatic":
            M[:3, 3] = value * self.joints[k].axis
        else:
            M[:3, :3] += math.sin(value) * self._K[k] + (1.0 - math.cos(value)) * self._K2[k]
        return M

    def forward_all(self, q: np.ndarray) -> list[np.ndarray]:
        """T_base_link for each joint's child link, arrays, shape (4, 4), frame base."""
        out, T, i = [], np.eye(4), 0
        for k, joint in enumerate(self.joints):
            T = T @ joint.origin
            if joint.movable:
                T = T @ self._motion(k, q[i])
                i += 1
            out.append(T)
        return out

    def frames(self, q: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """T_base_tip, array, shape (4, 4); each movable joint's origin, array, shape (n, 3),
        metres, and unit axis, array, shape (n, 3); all in frame base."""
        n = self.dof
        P, Z = np.empty((n, 3)), np.empty((n, 3))
        T, i = np.eye(4), 0
        for k, joint in enumerate(self.joints):
            T = T @ joint.origin
            if joint.movable:
                P[i] = T[:3, 3]
                Z[i] = T[:3, :3] @ joint.axis
                T = T @ self._motion(k, q[i])
                i += 1
        return T, P, Z

    def jacobian_at(self, T: np.ndarray, P: np.ndarray, Z: np.ndarray) -> np.ndarray:
        """Geometric Jacobian, shape (6, n): rows linear (m per unit q) then angular velocity
        (rad/s per unit q) of the tip, both in frame base, from the output of `frames`."""
        J = np.empty((6, self.dof))
        J[:3] = np.where(self._prismatic[:, None], Z, np.cross(Z, T[:3, 3] - P)).T
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

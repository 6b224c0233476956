"""The simulated scene: the arm on its mount, the seabed and the object, in PyBullet.

No bus here: :class:`SimWorld` is driven by method calls (the service, the experiment and the
tests drive it alike). Frame ``world`` (the tank, z up), metres, seconds on the recording clock.

Gravity is off: underwater, the arm's buoyancy and its controllers hold it, and the object is
carried along its recorded path by a constraint whose force is bounded (``drive_force_n``), so
a gripper that hits it pushes it aside as the water would let it.

The object is the recording's own (its scenario's shape, as a convex hull) where the recording
says; else it starts as the sphere or cylinder perception fitted and becomes perception's mesh
(its convex hull) once one arrives. Its tether runs straight from its lower end (along its
−z) to an anchor on the seabed, fixed where that line met the seabed when the scene was
built; the tether is a thin line that pushes nothing, but an arm link touching it is
recorded (:meth:`SimWorld.tether_touches`) while :attr:`SimWorld.watch_tether` is set.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import pybullet as pb
from scipy.spatial.transform import Rotation

from wavegrasp.arm import ArmModel

STEP_S = 1.0 / 240.0
TETHER_RADIUS_M = 0.003


@dataclass(frozen=True)
class ObjectShape:
    """``shape`` 'sphere' or another (a cylinder along the object's z, unless ``vertices``);
    radius and length, metres. ``vertices`` : array, shape (v, 3), metres, frame object
    (origin at the volume centroid): the object is their convex hull. ``tether_m``: from the
    centroid to the tether's attachment (default: half the length, a sphere's radius)."""

    shape: str
    radius_m: float
    length_m: float
    mass_kg: float = 0.15
    vertices: np.ndarray | None = field(default=None, compare=False)
    tether_m: float | None = None

    @property
    def tether_offset_m(self) -> float:
        """From the centroid to the tether's attachment, along the object's −z."""
        if self.tether_m is not None:
            return self.tether_m
        return self.radius_m if self.shape == "sphere" else self.length_m / 2


class SimWorld:
    """PyBullet in DIRECT mode (``gui=True`` opens a window for people with a screen).

    arm : the model the planner uses (its URDF is loaded here); T_world_base : array, shape
    (4, 4), where its base link is mounted.
    """

    def __init__(self, arm: ArmModel, T_world_base: np.ndarray, obj: ObjectShape,
                 drive_force_n: float = 5.0, gui: bool = False) -> None:
        self.arm, self.drive_force_n = arm, drive_force_n
        self.client = pb.connect(pb.GUI if gui else pb.DIRECT)
        c = self.client
        pb.setGravity(0.0, 0.0, 0.0, physicsClientId=c)
        pb.setTimeStep(STEP_S, physicsClientId=c)
        self.time_s = 0.0
        quat = Rotation.from_matrix(T_world_base[:3, :3]).as_quat().tolist()
        self.robot = pb.loadURDF(str(arm.urdf_path), T_world_base[:3, 3].tolist(), quat,
                                 useFixedBase=True, physicsClientId=c)
        info = [pb.getJointInfo(self.robot, i, physicsClientId=c)
                for i in range(pb.getNumJoints(self.robot, physicsClientId=c))]
        names = {i[1].decode(): i[0] for i in info}
        #: PyBullet link index -> link name (-1 is the base link).
        self.link_names = {i[0]: i[12].decode() for i in info} | {-1: arm.base_link}
        self.tool_link = {name: i for i, name in self.link_names.items()}[arm.tool_link]
        self.joints = [names[n] for n in arm.joint_names]
        self.fingers = [names[n] for n in arm.jaw_joints]
        self.finger_links = set(self.fingers)  # a joint's index is its child link's
        self._effort = [pb.getJointInfo(self.robot, i, physicsClientId=c)[10]
                        for i in self.joints + self.fingers]
        floor = pb.createCollisionShape(pb.GEOM_PLANE, physicsClientId=c)
        self.seabed = pb.createMultiBody(0.0, floor, physicsClientId=c)
        if obj.vertices is not None:
            shape = pb.createCollisionShape(pb.GEOM_MESH, vertices=np.asarray(
                obj.vertices, dtype=float).tolist(), physicsClientId=c)
        elif obj.shape == "sphere":
            shape = pb.createCollisionShape(pb.GEOM_SPHERE, radius=obj.radius_m,
                                            physicsClientId=c)
        else:
            shape = pb.createCollisionShape(pb.GEOM_CYLINDER, radius=obj.radius_m,
                                            height=obj.length_m, physicsClientId=c)
        self.obj = obj
        self.object = self._add_object(shape, [0.0, 0.0, 0.5], [0.0, 0.0, 0.0, 1.0])
        for link in self.finger_links:
            pb.changeDynamics(self.robot, link, lateralFriction=0.9, physicsClientId=c)
        self.tether: int | None = None
        self.anchor: np.ndarray | None = None
        self._tether_length = 0.0
        self._tether_touched: set[int] = set()
        #: Whether each step places the tether and records the links touching it: only
        #: while someone reads them (an attempt before its grasp). The tether follows the
        #: object step by step then; idle, its two calls a step were half the sim's steps.
        self.watch_tether = False
        self.set_arm(arm.q_home)
        self.set_jaw(arm.jaw_max_opening_m)

    def _add_object(self, shape: int, position: list[float], quat: list[float]) -> int:
        c = self.client
        body = pb.createMultiBody(self.obj.mass_kg, shape, basePosition=position,
                                  baseOrientation=quat, physicsClientId=c)
        pb.changeDynamics(body, -1, lateralFriction=0.8, linearDamping=0.0,
                          angularDamping=0.0, physicsClientId=c)
        self._drive = pb.createConstraint(body, -1, -1, -1, pb.JOINT_FIXED, [0, 0, 0],
                                          [0, 0, 0], position, physicsClientId=c)
        pb.changeConstraint(self._drive, position, jointChildFrameOrientation=quat,
                            maxForce=self.drive_force_n, physicsClientId=c)
        return int(body)

    def use_mesh(self, vertices: np.ndarray) -> None:
        """Make the object perception's mesh (its convex hull), where the object is now.

        vertices : array, shape (v, 3), metres, frame object (origin at the centroid).
        """
        v = np.asarray(vertices, dtype=float)
        if v.ndim != 2 or v.shape[1] != 3 or len(v) < 4 or not np.all(np.isfinite(v)):
            raise ValueError(f"mesh vertices must be finite with shape (v >= 4, 3), got {v.shape}")
        c = self.client
        position, quat = pb.getBasePositionAndOrientation(self.object, physicsClientId=c)
        linear, angular = pb.getBaseVelocity(self.object, physicsClientId=c)
        target = pb.getConstraintInfo(self._drive, physicsClientId=c)
        pb.removeConstraint(self._drive, physicsClientId=c)
        pb.removeBody(self.object, physicsClientId=c)
        shape = pb.createCollisionShape(pb.GEOM_MESH, vertices=v.tolist(), physicsClientId=c)
        self.object = self._add_object(shape, list(position), list(quat))
        pb.resetBaseVelocity(self.object, linear, angular, physicsClientId=c)
        # Keep pulling towards where the water carries it, not where it happens to be.
        pb.changeConstraint(self._drive, list(target[7]), jointChildFrameOrientation=list(
            target[9]), maxForce=self.drive_force_n, physicsClientId=c)

    def add_tether(self) -> bool:
        """Anchor a tether where the line down the object's −z from its attachment meets the
        seabed (z = 0); False if that line does not reach the seabed."""
        attach, down = self._attachment()
        if down[2] > -0.2 or attach[2] <= 0.0:
            return False
        self.anchor = attach + down * (attach[2] / -down[2])
        self._tether_length = float(np.linalg.norm(self.anchor - attach))
        shape = pb.createCollisionShape(pb.GEOM_CAPSULE, radius=TETHER_RADIUS_M,
                                        height=self._tether_length, physicsClientId=self.client)
        self.tether = int(pb.createMultiBody(0.0, shape, physicsClientId=self.client))
        # A string pushes nothing: no contacts; touches are found by distance queries.
        pb.setCollisionFilterGroupMask(self.tether, -1, 0, 0, physicsClientId=self.client)
        self._place_tether()
        return True

    def _attachment(self) -> tuple[np.ndarray, np.ndarray]:
        """The tether's attachment point and the object's −z, world."""
        position, quat = pb.getBasePositionAndOrientation(self.object,
                                                          physicsClientId=self.client)
        # PyBullet's own conversion, and the formula below rather than scipy's
        # align_vectors (~110 µs a call against ~5 µs): both run every physics step, and
        # with scipy they took 40 % of the sim's CPU (18.7 s in a 20-trial run, now 11.4 s).
        m = pb.getMatrixFromQuaternion(quat)  # row-major 3 x 3
        down = -np.array([m[2], m[5], m[8]])
        return np.array(position) + self.obj.tether_offset_m * down, down

    def _place_tether(self) -> None:
        """The tether from its anchor towards the attachment (straight; taut or not)."""
        assert self.tether is not None and self.anchor is not None
        attach, _ = self._attachment()
        up = attach - self.anchor
        up /= max(float(np.linalg.norm(up)), 1e-9)
        # The shortest turn of z onto up: axis z × up, half-angle form (x, y, z, w).
        quat = [-up[1], up[0], 0.0, 1.0 + up[2]] if up[2] > -1.0 + 1e-9 else [1.0, 0, 0, 0]
        quat = (np.array(quat) / np.linalg.norm(quat)).tolist()
        centre = self.anchor + up * self._tether_length / 2
        pb.resetBasePositionAndOrientation(self.tether, centre.tolist(), quat,
                                           physicsClientId=self.client)

    # --- commands -----------------------------------------------------------------------

    def place_object(self, position: np.ndarray, quat_xyzw: np.ndarray) -> None:
        """Put the object at a pose at once (at the start, or when the drive jumps)."""
        pb.resetBasePositionAndOrientation(self.object, position.tolist(), quat_xyzw.tolist(),
                                           physicsClientId=self.client)
        self.drive_object(position, quat_xyzw)

    def drive_object(self, position: np.ndarray, quat_xyzw: np.ndarray) -> None:
        """Where the water carries the object now (its recorded pose), with bounded force."""
        pb.changeConstraint(self._drive, position.tolist(), jointChildFrameOrientation=(
            quat_xyzw.tolist()), maxForce=self.drive_force_n, physicsClientId=self.client)

    def set_arm(self, q: np.ndarray) -> None:
        """Put the arm at ``q`` (radians) at once and hold it there."""
        for index, value in zip(self.joints, q, strict=True):
            pb.resetJointState(self.robot, index, float(value), physicsClientId=self.client)
        self.command_arm(q, np.zeros(len(q)))

    def command_arm(self, q: np.ndarray, qd: np.ndarray) -> None:
        """Position control towards ``q`` with feed-forward velocity ``qd`` (rad/s)."""
        for k, index in enumerate(self.joints):
            pb.setJointMotorControl2(self.robot, index, pb.POSITION_CONTROL, float(q[k]),
                                     float(qd[k]), force=self._effort[k], positionGain=0.3,
                                     velocityGain=1.0, physicsClientId=self.client)

    def set_jaw(self, opening_m: float) -> None:
        """Drive the fingers towards a gap of ``opening_m`` at their speed and force limits."""
        self.set_fingers(np.full(len(self.fingers), opening_m / len(self.fingers)))

    def set_fingers(self, positions: np.ndarray) -> None:
        """Drive each finger joint towards its position (m; shape (f,), ``arm.jaw_joints``'
        order, within their limits) at its speed and force limits."""
        for k, index in enumerate(self.fingers):
            lim = self.arm.joints[self.arm.jaw_joints[k]]
            target = float(np.clip(positions[k], lim.lower, lim.upper))
            pb.setJointMotorControl2(self.robot, index, pb.POSITION_CONTROL, target,
                                     force=self._effort[len(self.joints) + k],
                                     maxVelocity=lim.max_velocity, physicsClientId=self.client)

    def step_to(self, t_s: float) -> None:
        """Advance the simulation to ``t_s`` (recording seconds) in fixed steps."""
        while self.time_s + STEP_S <= t_s + 1e-12:
            pb.stepSimulation(physicsClientId=self.client)
            self.time_s += STEP_S
            if self.tether is not None and self.watch_tether:
                self._place_tether()
                self._tether_touched.update(p[3] for p in pb.getClosestPoints(
                    self.robot, self.tether, 0.0, physicsClientId=self.client))

    # --- state --------------------------------------------------------------------------

    def arm_q(self) -> tuple[np.ndarray, np.ndarray]:
        states = pb.getJointStates(self.robot, self.joints, physicsClientId=self.client)
        return np.array([s[0] for s in states]), np.array([s[1] for s in states])

    def finger_q(self) -> tuple[np.ndarray, np.ndarray]:
        """The jaw's finger joints (``arm.jaw_joints``): positions (m) and velocities (m/s)."""
        states = pb.getJointStates(self.robot, self.fingers, physicsClientId=self.client)
        return np.array([s[0] for s in states]), np.array([s[1] for s in states])

    def jaw_opening(self) -> float:
        states = pb.getJointStates(self.robot, self.fingers, physicsClientId=self.client)
        return float(sum(s[0] for s in states))

    def object_position(self) -> np.ndarray:
        return np.array(pb.getBasePositionAndOrientation(self.object,
                                                          physicsClientId=self.client)[0])

    def tool_position(self) -> np.ndarray:
        """The grasp point between the jaws, metres, world."""
        return self.tool_pose()[0]

    def tool_pose(self) -> tuple[np.ndarray, np.ndarray]:
        """The grasp point (3,), metres, world, and the tool's axes, shape (3, 3), columns x
        (the jaws close along it), y, z (the approach) in world."""
        state = pb.getLinkState(self.robot, self.tool_link, computeForwardKinematics=True,
                                physicsClientId=self.client)
        R = np.array(pb.getMatrixFromQuaternion(state[5])).reshape(3, 3)
        return np.array(state[4]), R

    def contacts(self) -> set[int]:
        """The arm's links (PyBullet indices) touching the object now."""
        return {c[3] for c in pb.getContactPoints(self.robot, self.object,
                                                  physicsClientId=self.client)}

    def tether_touches(self) -> set[int]:
        """The arm's links (PyBullet indices) that touched the tether since the last call."""
        touched, self._tether_touched = self._tether_touched, set()
        return touched

    def close(self) -> None:
        if pb.isConnected(physicsClientId=self.client):
            pb.disconnect(physicsClientId=self.client)


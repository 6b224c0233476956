"""The manipulator: a Bravo-7-class arm's kinematics, read from a URDF (``wavegrasp.arm``).

``bravo7_like.urdf``: wavegrasp's own Bravo-7-like model (6 revolute joints, a two-finger
parallel jaw, a ``tool`` frame at the grasp point: z the approach, x the jaws' closing
direction), used unless a URDF of the real arm is given.
``model``: :class:`ArmModel` (limits, forward and inverse kinematics, Jacobian, link
capsules) and :class:`Joint`. ``urdf``: the URDF reader. ``ik``: the damped least-squares
solver.
"""

from wavegrasp.arm.model import DEFAULT_URDF, ArmModel, Joint

__all__ = ["ArmModel", "Joint", "DEFAULT_URDF"]

"""Joint limits from a URDF: position and velocity from <limit>, acceleration and jerk from
wavegrasp's <limits> elements or, for a URDF without them, documented defaults."""

from __future__ import annotations

from dataclasses import dataclass, fields, replace

from wavegrasp.arm.urdf import UrdfJoint
from wavegrasp.checks import check_positive

#: Defaults for a URDF that does not state a limit (or states velocity="0"): per joint type,
#: rad/s, rad/s^2, rad/s^3 for revolute joints and m/s, m/s^2, m/s^3 for prismatic ones.
#: Cautious values at the low end of a Bravo-7-class arm's.
DEFAULTS = {
    "revolute": {"max_velocity": 1.0, "max_acceleration": 3.0, "max_jerk": 30.0},
    "prismatic": {"max_velocity": 0.05, "max_acceleration": 0.5, "max_jerk": 5.0},
}


@dataclass(frozen=True)
class Joint:
    """Limits of one joint: position [lower, upper] in radians (metres for a prismatic
    joint), max_velocity in rad/s (m/s), max_acceleration in rad/s^2 (m/s^2), max_jerk in
    rad/s^3 (m/s^3)."""

    name: str
    lower: float
    upper: float
    max_velocity: float
    max_acceleration: float
    max_jerk: float

    def check(self) -> Joint:
        """Return self; raise ValueError naming the joint if a limit is unusable."""
        if not self.lower <= self.upper:
            raise ValueError(f"joint {self.name!r}: lower {self.lower} > upper {self.upper}")
        for key in ("max_velocity", "max_acceleration", "max_jerk"):
            check_positive(f"joint {self.name!r} {key}", getattr(self, key))
        return self


def joint_limits(joint: UrdfJoint, extra: dict[str, float]) -> Joint:
    """The limits of a movable URDF joint, with `extra` holding acceleration and jerk."""
    defaults = DEFAULTS["prismatic" if joint.type == "prismatic" else "revolute"]
    return Joint(joint.name, joint.lower, joint.upper,
                 joint.velocity if joint.velocity > 0 else defaults["max_velocity"],
                 extra.get("acceleration", defaults["max_acceleration"]),
                 extra.get("jerk", defaults["max_jerk"])).check()


def apply_overrides(joints: dict[str, Joint],
                    overrides: dict[str, dict[str, float]] | None) -> dict[str, Joint]:
    """`joints` with limits replaced, e.g. {"wrist_roll": {"max_velocity": 0.5}}."""
    out = dict(joints)
    allowed = {f.name for f in fields(Joint)} - {"name"}
    for name, values in (overrides or {}).items():
        if name not in out:
            raise ValueError(f"override for unknown joint {name!r}; joints are {list(out)}")
        unknown = set(values) - allowed
        if unknown:
            raise ValueError(f"override for joint {name!r}: unknown fields {sorted(unknown)}, "
                             f"allowed are {sorted(allowed)}")
        out[name] = replace(out[name], **{k: float(v) for k, v in values.items()}).check()
    return out

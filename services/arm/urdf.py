"""A small URDF reader (xml.etree, no ROS): joints, the chain from base to tool, link shapes.

Besides standard URDF it reads wavegrasp's own block, which URDF parsers ignore::

    <wavegrasp>
      <limits joint="base_yaw" acceleration="4" jerk="40"/>   <!-- rad/s^2, rad/s^3 -->
      <jaw joints="finger_left finger_right" max_opening="0.14"/>   <!-- metres -->
      <home q="0 -1.0 2.0 0 -1.0 0"/>   <!-- radians, one value per arm joint -->
    </wavegrasp>
"""

from __future__ import annotations

import math
import xml.etree.ElementTree as ET
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from wavegrasp.arm.transforms import rpy_matrix

#: Limits of a continuous joint, radians (finite, so trajectory generators can use them).
CONTINUOUS_LIMIT = 2 * math.pi
#: Radius (m) of the capsule for a link whose collision geometry is a mesh.
DEFAULT_RADIUS = 0.05


@dataclass(frozen=True)
class UrdfJoint:
    """One URDF joint. origin : array, shape (4, 4), the child joint frame in frame `parent`;
    axis : array, shape (3,), unit, in the joint frame; limits in radians or metres."""

    name: str
    type: str
    parent: str
    child: str
    origin: np.ndarray
    axis: np.ndarray
    lower: float = 0.0
    upper: float = 0.0
    velocity: float = 0.0

    @property
    def movable(self) -> bool:
        return self.type in ("revolute", "continuous", "prismatic")


@dataclass(frozen=True)
class Capsule:
    """A segment p0-p1 (arrays, shape (3,), metres, in the link's frame) swept by a sphere of
    `radius` metres."""

    p0: np.ndarray
    p1: np.ndarray
    radius: float


@dataclass
class UrdfRobot:
    """A parsed URDF: links with their collision capsules, joints, and the wavegrasp block."""

    name: str
    links: dict[str, list[Capsule]]
    joints: dict[str, UrdfJoint]
    extra_limits: dict[str, dict[str, float]] = field(default_factory=dict)
    jaw_joints: list[str] | None = None
    jaw_max_opening: float | None = None
    home: np.ndarray | None = None

    def root(self) -> str:
        """The link that is no joint's child."""
        children = {j.child for j in self.joints.values()}
        roots = [name for name in self.links if name not in children]
        if len(roots) != 1:
            raise ValueError(f"URDF {self.name!r} must have exactly one root link, has {roots}")
        return roots[0]

    def chain(self, base: str, tip: str) -> list[UrdfJoint]:
        """The joints from link `base` down to link `tip`, in order."""
        for name in (base, tip):
            if name not in self.links:
                raise ValueError(f"URDF {self.name!r} has no link {name!r}")
        by_child = {j.child: j for j in self.joints.values()}
        out: list[UrdfJoint] = []
        link = tip
        while link != base:
            if link not in by_child:
                raise ValueError(f"link {tip!r} is not below link {base!r} in {self.name!r}")
            out.append(by_child[link])
            link = by_child[link].parent
        return out[::-1]


def _floats(text: str | None, n: int, default: float = 0.0) -> np.ndarray:
    if text is None:
        return np.full(n, default)
    values = np.array([float(v) for v in text.split()])
    if values.shape != (n,):
        raise ValueError(f"expected {n} numbers, got {text!r}")
    return values


def _origin(el: ET.Element | None) -> np.ndarray:
    T = np.eye(4)
    if el is not None:
        T[:3, :3] = rpy_matrix(_floats(el.get("rpy"), 3))
        T[:3, 3] = _floats(el.get("xyz"), 3)
    return T


def _capsules(link: ET.Element) -> list[Capsule]:
    """Capsules around the link's collision shapes: a cylinder's axis, a box's longest edge
    (:func:`_box_capsules`), a sphere's centre; meshes are left out."""
    out = []
    for col in link.findall("collision"):
        T = _origin(col.find("origin"))
        geom = col.find("geometry")
        shape = geom[0] if geom is not None and len(geom) else None
        if shape is None:
            continue
        centre, R = T[:3, 3], T[:3, :3]
        if shape.tag == "cylinder":
            half = float(shape.get("length", 0.0)) / 2
            radius = float(shape.get("radius", DEFAULT_RADIUS))
            out.append(Capsule(centre - half * R[:, 2], centre + half * R[:, 2], radius))
        elif shape.tag == "box":
            out += _box_capsules(centre, R, _floats(shape.get("size"), 3))
        elif shape.tag == "sphere":
            out.append(Capsule(centre, centre.copy(), float(shape.get("radius", 0.0))))
    return out


def _box_capsules(centre: np.ndarray, R: np.ndarray, size: np.ndarray) -> list[Capsule]:
    """Capsules along a box's longest edge that together enclose it: side by side across
    its middle edge, as many as that edge is times its shortest, each just round its slice.
    A flat box (a jaw's finger, 1.5 cm thick and 4 cm tall) is then no thicker than it is;
    one capsule round the whole cross-section would make a finger 4.3 cm thick and close the
    jaw's 14 cm gap to 11 cm. centre : (3,), R : (3, 3), size : (3,), metres, link frame."""
    long, short, mid = int(np.argmax(size)), int(np.argmin(size)), 0
    mid = 3 - long - short if long != short else (long + 1) % 3
    count = max(1, int(np.ceil(size[mid] / size[short] - 1e-9)))
    step = size[mid] / count
    radius = float(np.hypot(size[short], step)) / 2
    half = size[long] / 2 * R[:, long]
    out = []
    for i in range(count):
        c = centre + (-size[mid] / 2 + (i + 0.5) * step) * R[:, mid]
        out.append(Capsule(c - half, c + half, radius))
    return out


def _joint(el: ET.Element) -> UrdfJoint:
    name, kind = el.get("name", ""), el.get("type", "")
    parent, child = el.find("parent"), el.find("child")
    if parent is None or child is None:
        raise ValueError(f"joint {name!r} needs <parent> and <child>")
    axis_el = el.find("axis")
    text = axis_el.get("xyz") if axis_el is not None else None
    axis = _floats(text, 3) if text else np.array([1.0, 0.0, 0.0])  # URDF's default axis
    norm = np.linalg.norm(axis)
    if kind != "fixed" and norm == 0:
        raise ValueError(f"joint {name!r} has a zero axis")
    axis = axis / norm if norm else axis
    lim = el.find("limit")
    lower = float(lim.get("lower", 0.0)) if lim is not None else 0.0
    upper = float(lim.get("upper", 0.0)) if lim is not None else 0.0
    velocity = float(lim.get("velocity", 0.0)) if lim is not None else 0.0
    if kind == "continuous":
        lower, upper = -CONTINUOUS_LIMIT, CONTINUOUS_LIMIT
    return UrdfJoint(name, kind, parent.get("link", ""), child.get("link", ""),
                     _origin(el.find("origin")), axis, lower, upper, velocity)


def parse_urdf(path: str | Path) -> UrdfRobot:
    """Read the URDF file at `path`; raise ValueError if it is not a usable robot."""
    try:
        root = ET.parse(path).getroot()
    except ET.ParseError as e:
        raise ValueError(f"{path}: not valid XML: {e}") from e
    if root.tag != "robot":
        raise ValueError(f"{path}: root element is <{root.tag}>, expected <robot>")
    robot = UrdfRobot(root.get("name", ""), {el.get("name", ""): _capsules(el)
                                             for el in root.findall("link")},
                      {j.name: j for j in map(_joint, root.findall("joint"))})
    for block in root.findall("wavegrasp"):
        for el in block.findall("limits"):
            robot.extra_limits[el.get("joint", "")] = {
                k: float(el.get(k)) for k in ("acceleration", "jerk") if el.get(k) is not None}
        jaw = block.find("jaw")
        if jaw is not None:
            robot.jaw_joints = jaw.get("joints", "").split()
            if jaw.get("max_opening") is not None:
                robot.jaw_max_opening = float(jaw.get("max_opening"))
        home = block.find("home")
        if home is not None:
            robot.home = np.array([float(v) for v in home.get("q", "").split()])
    return robot

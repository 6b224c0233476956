"""A buoyant object on a tether anchored to the seabed, driven by the orbital flow.

The body is a point mass at its volume centroid with net buoyancy, added mass, Morison drag
and inertia (Froude-Krylov plus added mass) in the flow of a :class:`~.waves.Sea`. The tether
is inextensible and can only pull: while taut the centroid stays on a sphere of radius
``tether_length + attach_offset`` around the anchor (the paper's section IV-C); when the tether
would have to push (a body that is not buoyant enough) it goes slack and the body moves freely
inside that sphere. The body's axis points along the tether.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import numpy as np

from wavegrasp.checks import check_positive
from wavegrasp.wavetank.waves import RHO, G, Sea


@dataclass(frozen=True)
class ObjectSpec:
    """An object configuration. Lengths metres, mass kg, volume m³ (displaced, sealed)."""

    name: str
    shape: str  # sphere, cylinder, ellipsoid, box or bottle; the axis along the tether (body z)
    radius: float  # half the width across (a box: along body x)
    length: float  # along the axis; 2·radius for a sphere
    mass: float
    volume: float
    drag_coefficient: float
    added_mass_coefficient: float
    description: str
    depth: float = 0.0  # a box: its extent along body y
    neck_radius: float = 0.0  # a bottle: its neck ...
    neck_length: float = 0.0  # ... and the neck's length (a 45° shoulder joins it to the body)
    neck_down: bool = True  # a bottle: the neck at the tether's end (tethered at the cap)
    turn_deg: float = 0.0  # turned about its axis (a box's faces), degrees

    def profile(self) -> tuple[np.ndarray, np.ndarray]:
        """An axisymmetric object's outline: heights z from its lower end (the tether's end)
        and radii r there, metres, shape (k,) each; ValueError for a box."""
        return profile(self)

    @property
    def attach_offset(self) -> float:
        """Distance from the tether's attachment point to the volume centroid, metres."""
        if self.shape != "bottle":
            return self.length / 2
        return solid_of_revolution(*self.profile())[1]

    @property
    def projected_area(self) -> float:
        """Frontal area for drag, m² (across the axis; a box: its faces' mean)."""
        if self.shape == "box":
            return self.length * (2 * self.radius + self.depth) / 2
        if self.shape in ("sphere", "ellipsoid"):  # an ellipse's area, exactly
            return np.pi * self.radius * self.length / 2
        z, r = self.profile()
        return float(np.sum(np.diff(z) * (r[1:] + r[:-1])))

    @property
    def grasp_width(self) -> float:
        """The narrowest a jaw closing across the object's axis can take it, metres: a box
        between its nearer pair of faces, anything else across its widest."""
        return min(2 * self.radius, self.depth) if self.shape == "box" else 2 * self.radius

    @property
    def bounding_radius(self) -> float:
        """Radius of the smallest sphere about the volume centroid that holds it, metres."""
        if self.shape == "box":
            return 0.5 * float(np.linalg.norm([2 * self.radius, self.depth, self.length]))
        z, r = self.profile()
        return float(np.max(np.hypot(r, z - self.attach_offset)))

    @property
    def net_buoyancy(self) -> float:
        """Upward force in still water, newtons (negative: it sinks)."""
        return (RHO * self.volume - self.mass) * G

    def scaled(self, factor: float) -> ObjectSpec:
        """The same object ``factor`` times larger (mass scales with volume)."""
        check_positive("scale", factor)
        return dataclasses.replace(
            self, name=f"{self.name}x{factor:g}", radius=self.radius * factor,
            length=self.length * factor, mass=self.mass * factor**3,
            volume=self.volume * factor**3, depth=self.depth * factor,
            neck_radius=self.neck_radius * factor, neck_length=self.neck_length * factor)


def profile(spec: ObjectSpec, samples: int = 65) -> tuple[np.ndarray, np.ndarray]:
    """See :meth:`ObjectSpec.profile`; ``samples`` heights for a sphere or an ellipsoid."""
    r0, length = spec.radius, spec.length
    if spec.shape in ("sphere", "ellipsoid"):
        theta = np.linspace(np.pi, 0.0, samples)
        return length / 2 * (1 + np.cos(theta)), r0 * np.sin(theta)
    if spec.shape == "cylinder":
        return np.array([0.0, length]), np.array([r0, r0])
    if spec.shape == "bottle":
        neck, shoulder = spec.neck_length, spec.neck_length + (r0 - spec.neck_radius)
        z = np.array([0.0, neck, shoulder, length])
        r = np.array([spec.neck_radius, spec.neck_radius, r0, r0])
        return (z, r) if spec.neck_down else (length - z[::-1], r[::-1])
    raise ValueError(f"shape {spec.shape!r} has no profile (not a solid of revolution)")


def solid_of_revolution(z: np.ndarray, r: np.ndarray) -> tuple[float, float]:
    """Volume (m³) and the volume centroid's height (metres, from z[0]) of the solid that the
    outline ``z``, ``r`` (shape (k,) each, z ascending) sweeps about its axis: frusta summed."""
    z, r = np.asarray(z, dtype=float), np.asarray(r, dtype=float)
    h, a, b = np.diff(z), r[:-1], r[1:]
    s = a * a + a * b + b * b
    volume = np.pi * h * s / 3
    centroid = z[:-1] + np.divide(h * (a * a + 2 * a * b + 3 * b * b), 4 * s,
                                  out=h / 2, where=s > 0)
    total = float(volume.sum())
    return total, float(volume @ centroid / total) - float(z[0])


def _cylinder(name: str, radius: float, length: float, mass: float, cd: float, ca: float,
              description: str) -> ObjectSpec:
    return ObjectSpec(name, "cylinder", radius, length, mass, np.pi * radius**2 * length,
                      cd, ca, description)


OBJECTS: dict[str, ObjectSpec] = {
    # Cd and Ca of short cylinders in cross-flow fall with the aspect ratio (DNV-RP-C205).
    "bottle": _cylinder("bottle", 0.032, 0.160, 0.025, 0.9, 0.8,
                        "inverted 0.5 L PET bottle, sealed, air-filled; tethered at the cap"),
    "can_empty": _cylinder("can_empty", 0.033, 0.122, 0.015, 0.8, 0.6,
                           "355 ml aluminium can, empty and sealed; tethered at one end"),
    "can_half": _cylinder("can_half", 0.033, 0.122, 0.015 + 0.1775, 0.8, 0.6,
                          "the same can, half full of water (177.5 g)"),
    "buoy": ObjectSpec("buoy", "sphere", 0.06, 0.12, 0.15, 4 / 3 * np.pi * 0.06**3, 0.5, 0.5,
                       "small trawl-float buoy, 12 cm diameter, 150 g"),
}


def tether_quaternion(direction: np.ndarray) -> np.ndarray:
    """Orientation (x, y, z, w) whose body z axis points along ``direction`` (shape (3,)).

    The shortest rotation from +z; a tether pointing straight down turns about x.
    """
    n = direction / np.linalg.norm(direction)
    if n[2] < -1 + 1e-12:
        return np.array([1.0, 0.0, 0.0, 0.0])
    q = np.array([-n[1], n[0], 0.0, 1.0 + n[2]])
    return q / np.linalg.norm(q)


@dataclass
class TetheredBody:
    """State and dynamics of one tethered object. Positions metres in ``world``."""

    spec: ObjectSpec
    sea: Sea
    anchor: np.ndarray
    tether_length: float

    def __post_init__(self) -> None:
        check_positive("tether_length", self.tether_length)
        self.radius = self.tether_length + self.spec.attach_offset
        self.p = self.anchor + np.array([0.0, 0.0, self.radius])
        self.v = np.zeros(3)
        s = self.spec
        self.inertial_mass = s.mass + s.added_mass_coefficient * RHO * s.volume
        self._fk = RHO * s.volume * (1 + s.added_mass_coefficient)
        self._drag = 0.5 * RHO * s.drag_coefficient * s.projected_area
        self._weight = np.array([0.0, 0.0, s.net_buoyancy])
        self.slack_steps = 0
        self.steps = 0

    def force(self, t: float) -> np.ndarray:
        """Hydrodynamic + buoyancy force on the body (N), tether excluded."""
        u, a = self.sea.kinematics(t, self.p)
        rel = u - self.v
        return self._weight + self._fk * a + self._drag * math.sqrt(rel @ rel) * rel

    def step(self, t: float, dt: float) -> None:
        """Advance by ``dt`` seconds (semi-implicit Euler, tether as an exact constraint)."""
        acc = self.force(t) / self.inertial_mass
        r = self.p - self.anchor
        n = r / math.sqrt(r @ r)
        taut = math.sqrt(r @ r) >= self.radius - 1e-9
        if taut:
            vt = self.v - (self.v @ n) * n
            tension = acc @ n + (vt @ vt) / self.radius  # per unit inertial mass
            if tension > 0:
                acc = acc - tension * n
            else:
                taut = False
        self.slack_steps += not taut
        self.steps += 1
        self.v = self.v + acc * dt
        self.p = self.p + self.v * dt
        r = self.p - self.anchor
        dist = math.sqrt(r @ r)
        n = r / dist
        if taut or dist > self.radius:
            # Inextensible tether: back onto the sphere, no radial speed while it pulls.
            self.p = self.anchor + self.radius * n
            radial = float(self.v @ n)
            self.v = self.v - (radial if taut else max(0.0, radial)) * n

    @property
    def slack_fraction(self) -> float:
        """Fraction of steps so far during which the tether was slack."""
        return self.slack_steps / max(self.steps, 1)

    def orientation(self) -> np.ndarray:
        """Quaternion (x, y, z, w): body axis along the tether, from anchor to centroid."""
        return tether_quaternion(self.p - self.anchor)

    def tether_end(self) -> np.ndarray:
        """Where the tether meets the body, metres, world."""
        r = self.p - self.anchor
        return self.p - self.spec.attach_offset * r / np.linalg.norm(r)

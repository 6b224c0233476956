"""Random scenarios drawn from the ranges a user's vehicle, object and sea may span.

Ranges:
- sea: regular or JONSWAP (of those asked for, drawn alike), height (JONSWAP: significant
  height) 0.05-0.35 m, period (JONSWAP: peak period) 0.8-2.5 s, current 0-5 cm/s in any
  direction; the water 0.3-0.6 m deeper than the object's rest height;
- object: spheres 6-18 cm across, cylinders 4-12 cm across and 8-32 cm long; a third of the
  spheres are ellipsoids (0.6-1.7 times as long as wide), a third of the cylinders boxes (the
  third side 0.5-1 times the width, turned any way about its axis) and another third bottles
  (neck 0.3-0.5 of the width, down at the tether seven times in ten); 25-75 % of the
  displaced water's mass (buoyant enough to keep the tether taut); rest 0.3-0.7 m up;
- arm mount: its shoulder 0.4-0.85 m from the object's rest position, at any bearing, from 0.4 m
  below to 0.2 m above it, the mount turned -180..180 deg from facing it;
- camera: 0.5-1.6 m from the object at any bearing, 0-40 deg above it, looking at it; 5-30 Hz.

:func:`draw_scenarios` is deterministic in its seed. A draw that cannot be (the camera or the
mount out of the water, beyond the arm's reach) is refused by :class:`Scenario` and drawn
again; :func:`reach_verdict` says, from the arm model alone, whether the arm can reach the
object's whole swing.
"""

from __future__ import annotations

import math

import numpy as np
from pydantic import ValidationError

from wavegrasp.wavetank.scenario import (
    CameraSpec,
    MountSpec,
    ObjectModel,
    Scenario,
    SeaSpec,
    default_arm,
    describe,
)
from wavegrasp.wavetank.waves import wavenumber

RESOLUTIONS = ((320, 240), (256, 192), (400, 300))
RATES_HZ = (5.0, 10.0, 15.0, 20.0, 30.0)


def draw_object(rng: np.random.Generator, shapes: np.random.Generator) -> ObjectModel:
    """A sphere or a cylinder from ``rng``; ``shapes`` (its own generator, so that adding the
    other families left every other draw as it was) makes a third of the spheres ellipsoids,
    and a third of the cylinders boxes and another third bottles with a neck."""
    family = "sphere" if rng.random() < 0.5 else "cylinder"
    extra: dict[str, float | str] = {}
    if family == "sphere":
        d = rng.uniform(0.06, 0.18)
        length, cd, ca = None, 0.5, 0.5
        if shapes.random() < 1 / 3:
            family, length = "ellipsoid", d * shapes.uniform(0.6, 1.7)
    else:
        d, length = rng.uniform(0.04, 0.12), rng.uniform(0.08, 0.32)
        cd, ca = 0.8, 0.6
        pick = shapes.random()
        if pick < 1 / 3:
            family, extra = "box", {"depth_m": round(d * shapes.uniform(0.5, 1.0), 4),
                                    "turn_deg": round(shapes.uniform(-90.0, 90.0), 1)}
        elif pick < 2 / 3:
            neck = d * shapes.uniform(0.3, 0.5)
            room = length - (d - neck) / 2 - 0.02  # the body keeps at least 2 cm
            family, extra = "bottle", {
                "neck_diameter_m": round(neck, 4),
                "neck_length_m": round(max(0.005, room * shapes.uniform(0.2, 0.5)), 4),
                "neck": "down" if shapes.random() < 0.7 else "up"}
    fill = rng.uniform(0.25, 0.75)  # of the displaced water's mass
    obj = ObjectModel(family=family, diameter_m=round(d, 4),
                      length_m=None if length is None else round(length, 4), mass_kg=1.0,
                      rest_height_m=round(rng.uniform(0.3, 0.7), 3), drag_coefficient=cd,
                      added_mass_coefficient=ca, name=f"{family}-{d * 100:.0f}cm", **extra)
    return obj.model_copy(update={"mass_kg": round(1000.0 * obj.spec().volume * fill, 4)})


def mount_at(rest: np.ndarray, distance_m: float, bearing_deg: float, rise_m: float,
             yaw_offset_deg: float) -> MountSpec:
    """The mount that puts the arm's shoulder ``distance_m`` from the object's ``rest``
    (shape (3,), metres, world), at ``bearing_deg`` from it (0: along +x, the way the waves
    run) and ``rise_m`` above it, the arm turned ``yaw_offset_deg`` from facing it."""
    arm = default_arm()
    bearing = math.radians(bearing_deg)
    across = math.sqrt(max(distance_m**2 - rise_m**2, 1e-6))
    shoulder = rest + np.array([across * math.cos(bearing), across * math.sin(bearing), rise_m])
    yaw = math.atan2(rest[1] - shoulder[1], rest[0] - shoulder[0]) + math.radians(yaw_offset_deg)
    c, s = math.cos(yaw), math.sin(yaw)
    base = shoulder - np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]) @ arm.shoulder
    # The yaw that faces the object from the base differs a little from the shoulder's.
    facing = math.atan2(rest[1] - base[1], rest[0] - base[0])
    return MountSpec(position=tuple(round(float(v), 4) for v in base),
                     yaw_offset_deg=round(math.degrees(yaw - facing), 2))


# Its own generator (from the scenario's seed) so that adding it left the other draws as
# they were.
CLOUDS = ("dense", "organized")
SEAS = ("regular", "jonswap")


def draw_scenario(rng: np.random.Generator, name: str, seconds: float, seed: int,
                  seas: tuple[str, ...] = ("regular",)) -> Scenario:
    """One draw, its sea of the kinds ``seas``; raises ValueError if it cannot be."""
    obj = draw_object(rng, np.random.default_rng([seed, 2]))
    rest = np.array([0.0, 0.0, obj.rest_height_m])
    depth = obj.rest_height_m + obj.bounding_radius_m + rng.uniform(0.3, 0.6)
    # The kind from a stream of its own, as the cloud's: a suite of regular seas alone is
    # the same draw as before irregular ones could be asked for.
    kind = seas[np.random.default_rng([seed, 3]).integers(len(seas))]
    sea = SeaSpec(kind=kind, height_m=round(rng.uniform(0.05, 0.35), 3),
                  period_s=round(rng.uniform(0.8, 2.5), 3), depth_m=round(depth, 3),
                  current_mps=round(rng.uniform(0.0, 0.05), 3),
                  current_deg=round(rng.uniform(-180, 180), 1))
    distance, bearing = rng.uniform(0.4, 0.85), rng.uniform(-180.0, 180.0)
    rise = rng.uniform(-0.4, 0.2)  # the shoulder's height above the object's rest
    mount = mount_at(rest, distance, bearing, rise, rng.uniform(-180.0, 180.0))
    cam_d, cam_b = rng.uniform(0.5, 1.6), rng.uniform(-math.pi, math.pi)
    cam_el = math.radians(rng.uniform(0.0, 40.0))
    eye = rest + cam_d * np.array([math.cos(cam_el) * math.cos(cam_b),
                                   math.cos(cam_el) * math.sin(cam_b), math.sin(cam_el)])
    width, height = RESOLUTIONS[rng.integers(len(RESOLUTIONS))]
    camera = CameraSpec(eye=tuple(round(float(v), 4) for v in eye),
                        target=tuple(float(v) for v in rest), width=width, height=height,
                        rate_hz=RATES_HZ[rng.integers(len(RATES_HZ))],
                        max_range_m=max(3.0, cam_d + 1.5),
                        cloud=CLOUDS[np.random.default_rng([seed, 1]).integers(len(CLOUDS))])
    return Scenario(name=name, sea=sea, object=obj, mount=mount, camera=camera,
                    seconds=seconds, seed=seed)


def draw_scenarios(n: int, seed: int, seconds: float = 60.0, max_tries: int = 50,
                   seas: tuple[str, ...] = ("regular",)) -> tuple[list[Scenario], list[str]]:
    """``n`` scenarios drawn with ``seed``, their seas of the kinds ``seas`` (:data:`SEAS`);
    also why the draws that could not be were not."""
    bad = [k for k in seas if k not in SEAS]
    if bad or not seas:
        raise ValueError(f"seas: unknown {', '.join(bad) or 'none given'}; known "
                         f"{', '.join(SEAS)}")
    rng = np.random.default_rng(seed)
    scenarios, refused = [], []
    for i in range(n):
        for _ in range(max_tries):
            try:
                scenarios.append(draw_scenario(rng, f"random-{seed}-{i:03d}", seconds,
                                               seed * 1000 + i, tuple(seas)))
                break
            except ValidationError as exc:
                refused.append(describe(exc))
        else:
            raise ValueError(f"no scenario could be drawn in {max_tries} tries")
    return scenarios, refused


def reach_verdict(s: Scenario) -> str | None:
    """Why the arm cannot reach the object over its whole swing, judged from the arm model
    (the shoulder's distance to the farthest point of the tether's sphere the wave may carry
    the object to), or None."""
    arm = default_arm()
    shoulder = s.shoulder()
    # The swing's horizontal half-width is at most the wave's orbital excursion at the
    # surface, a generous bound: H/2 / tanh(k h).
    k = wavenumber(2 * math.pi / s.sea.period_s, s.sea.depth_m)
    swing = s.sea.height_m / 2 / math.tanh(k * s.sea.depth_m)
    rest = s.rest
    farthest = float(np.linalg.norm(rest[:2] - shoulder[:2])) + swing
    distance = math.hypot(farthest, rest[2] - shoulder[2])
    if distance > arm.reach_m:
        return (f"the swing reaches {distance:.2f} m from the shoulder, beyond the arm's "
                f"{arm.reach_m:.2f} m")
    return None


def grasp_verdict(s: Scenario) -> str | None:
    """Why the arm cannot grasp the object at all, judged from the arm model alone: beyond
    its reach (:func:`reach_verdict`), or wider than its jaw opens however it takes it; or
    None."""
    reach = reach_verdict(s)
    if reach:
        return reach
    arm = default_arm()
    width = s.object.spec().grasp_width
    if width >= arm.jaw_max_opening_m:
        return (f"the object is {width * 100:.1f} cm across where the jaw would take it, the "
                f"jaw opens {arm.jaw_max_opening_m * 100:.1f} cm")
    return None

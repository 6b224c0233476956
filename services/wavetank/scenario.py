"""A scenario: everything a generated recording depends on, as one pydantic model.

Frame ``world``: origin on the seabed at the tether's anchor, z up, waves travelling along +x.
The object rests (tether taut and vertical) at ``(0, 0, object.rest_height_m)``; the arm's mount
``bravo_base_link`` and the camera are placed around it. ``wavegrasp record --scenario FILE``
reads one from YAML or JSON; the paper's twelve configurations are named scenarios
(:func:`paper_scenario`, ``paper-w1-buoy`` ...).

Only the recording's generator and the scoring read a scenario: perception, prediction,
planning and the gate see what a vehicle gives them (clouds, ``tf_static``, the arm).
"""

from __future__ import annotations

import dataclasses
import functools
import math
from pathlib import Path
from typing import Literal

import numpy as np
import yaml
from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

from wavegrasp.arm import ArmModel
from wavegrasp.wavetank.body import OBJECTS, ObjectSpec, solid_of_revolution
from wavegrasp.wavetank.waves import TABLE_I

Vec3 = tuple[float, float, float]

#: The paper's tank (see record.py's docstring).
TANK_DEPTH_M = 0.93
TANK_REST_HEIGHT_M = 0.525
PAPER_CAMERA_EYE: Vec3 = (0.0, -1.0, 0.75)
PAPER_CAMERA_TARGET: Vec3 = (0.0, 0.0, 0.5)
PAPER_MOUNT: Vec3 = (0.30, -0.60, 0.40)


class Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class SeaSpec(Strict):
    """The sea, in metres and seconds: a regular wave (with a small reflection, wave groups and
    the tank's slow flow) or a JONSWAP sea (see waves.py)."""

    kind: Literal["regular", "jonswap"] = "regular"
    height_m: float = Field(gt=0, le=1.0, description="crest to trough (jonswap: "
                            "significant height)")
    period_s: float = Field(gt=0.3, le=10.0, description="jonswap: peak period")
    depth_m: float = Field(TANK_DEPTH_M, gt=0.2, le=100.0, description="still water")
    current_mps: float = Field(0.01, ge=0, le=1.0, description="mean horizontal current")
    current_deg: float = Field(20.0, description="its direction, degrees from +x")


FAMILIES = ("sphere", "cylinder", "ellipsoid", "box", "bottle")


class ObjectModel(Strict):
    """The tethered object: its shape and size (metres), mass (kg) and tether.

    The object's axis runs along the tether. ``diameter_m`` is its width across (a box: along
    its x); ``length_m`` its length along the axis (an ellipsoid: that diameter; a bottle: cap
    to base). A box also has ``depth_m`` (along its y); a bottle a neck (``neck_diameter_m``,
    ``neck_length_m``, joined to the body by a 45° shoulder), down at the tether or up.
    """

    family: Literal["sphere", "cylinder", "ellipsoid", "box", "bottle"]
    diameter_m: float = Field(gt=0.01, le=0.5)
    length_m: float | None = Field(None, gt=0.01, le=1.0,
                                   description="length along the axis (the tether's direction)")
    depth_m: float | None = Field(None, gt=0.01, le=0.5, description="a box's third side")
    neck_diameter_m: float | None = Field(None, gt=0.005, le=0.3)
    neck_length_m: float | None = Field(None, gt=0.0, le=0.5)
    neck: Literal["down", "up"] = Field("down", description="a bottle's neck at the tether "
                                        "(tethered at the cap) or away from it")
    turn_deg: float = Field(0.0, ge=-180, le=180, description="the object turned about its "
                            "axis, degrees (which of a box's faces the camera sees)")
    mass_kg: float = Field(gt=0)
    rest_height_m: float = Field(TANK_REST_HEIGHT_M, gt=0.05, description="centroid above "
                                 "the seabed with the tether taut and vertical (the tether is "
                                 "this minus the attachment's offset from the centroid)")
    drag_coefficient: float = Field(0.8, gt=0, le=3)
    added_mass_coefficient: float = Field(0.6, ge=0, le=3)
    name: str = "object"

    @model_validator(mode="after")
    def _shape(self) -> ObjectModel:
        f = self.family
        if (f != "sphere") != (self.length_m is not None):
            raise ValueError(f"length_m: a {f} "
                             f"{'has none' if f == 'sphere' else 'needs one'} (a sphere has "
                             "none, every other family needs one)")
        if (f == "box") != (self.depth_m is not None):
            raise ValueError(f"depth_m: only a box has one (family {f})")
        necked = self.neck_diameter_m is not None and self.neck_length_m is not None
        if (f == "bottle") != necked or (f != "bottle" and (
                self.neck_diameter_m is not None or self.neck_length_m is not None)):
            raise ValueError(f"neck_diameter_m, neck_length_m: a bottle needs both, other "
                             f"families have neither (family {f})")
        if f == "bottle":
            assert self.length_m is not None and self.neck_diameter_m is not None
            if self.neck_diameter_m >= self.diameter_m:
                raise ValueError("neck_diameter_m: must be narrower than diameter_m")
            shoulder = (self.diameter_m - self.neck_diameter_m) / 2
            if self.neck_length_m + shoulder >= self.length_m - 0.01:
                raise ValueError("neck_length_m: the neck and its 45° shoulder leave no body "
                                 f"in a {self.length_m:g} m bottle")
        return self

    def spec(self) -> ObjectSpec:
        """The generator's physical description."""
        r, f = self.diameter_m / 2, self.family
        length = 2 * r if self.length_m is None else self.length_m
        spec = ObjectSpec(self.name, f, r, length, self.mass_kg, 0.0, self.drag_coefficient,
                          self.added_mass_coefficient, self.name, depth=self.depth_m or 0.0,
                          neck_radius=(self.neck_diameter_m or 0.0) / 2,
                          neck_length=self.neck_length_m or 0.0, neck_down=self.neck == "down",
                          turn_deg=self.turn_deg)
        if f == "box":
            volume = self.diameter_m * (self.depth_m or 0.0) * length
        elif f == "bottle":
            volume = solid_of_revolution(*spec.profile())[0]
        else:  # exact
            volume = math.pi * r**2 * length * (1.0 if f == "cylinder" else 2 / 3)
        return dataclasses.replace(spec, volume=volume)

    @property
    def bounding_radius_m(self) -> float:
        """Radius of the smallest sphere about the centroid that holds the object."""
        return self.spec().bounding_radius

    @classmethod
    def named(cls, name: str) -> ObjectModel:
        """One of the paper's objects (``bottle``, ``can_empty``, ``can_half``, ``buoy``)."""
        s = OBJECTS[name]
        return cls(family=s.shape, diameter_m=2 * s.radius,
                   length_m=None if s.shape == "sphere" else s.length, mass_kg=s.mass,
                   drag_coefficient=s.drag_coefficient,
                   added_mass_coefficient=s.added_mass_coefficient, name=name)


class MountSpec(Strict):
    """Where the arm's ``bravo_base_link`` is, in ``world`` (metres); its yaw turns it from
    facing the object's rest position (0: the arm faces it), degrees."""

    position: Vec3 = PAPER_MOUNT
    yaw_offset_deg: float = 0.0


class CameraSpec(Strict):
    """The stereo camera: where it is and looks (``world``, metres), its image and rate."""

    eye: Vec3 = PAPER_CAMERA_EYE
    target: Vec3 = PAPER_CAMERA_TARGET
    width: int = Field(320, ge=16, le=4096)
    height: int = Field(240, ge=12, le=4096)
    rate_hz: float = Field(10.0, gt=0, le=100)
    hfov_deg: float = Field(70.0, gt=0, lt=180)
    max_range_m: float = Field(3.0, gt=0)
    depth_sigma_at_1m: float = Field(0.0015, ge=0)
    dropout: float = Field(0.03, ge=0, le=1)
    dropout_blobs: int = Field(4, ge=0)
    snow_per_frame: int = Field(150, ge=0)
    # dense: height 1, valid points only; organized: height x width, NaN where stereo found
    # nothing, PCL's XYZRGB layout with padding, is_dense false (as stereo drivers publish).
    cloud: Literal["dense", "organized"] = "dense"

    def sensor(self) -> dict[str, float | int]:
        """The camera model's settings (TrisectCamera's fields but its pose)."""
        return self.model_dump(exclude={"eye", "target", "rate_hz", "cloud"})


class Scenario(Strict):
    """Everything a recording depends on. Times seconds, rates Hz."""

    name: str = "scenario"
    sea: SeaSpec
    object: ObjectModel
    mount: MountSpec = MountSpec()
    camera: CameraSpec = CameraSpec()
    seconds: float = Field(60.0, gt=0)
    seed: int = 0
    preroll_s: float = Field(30.0, ge=0)
    groundtruth_hz: float = Field(None, gt=0, description="default: the smallest multiple "
                                  "of the camera's rate from 100 Hz up")
    dt_s: float = Field(None, gt=0, le=0.01, description="physics step; default: about 2 ms, "
                        "a whole number of steps per ground-truth sample")

    @model_validator(mode="before")
    @classmethod
    def _rates(cls, values: object) -> object:
        if not isinstance(values, dict):
            return values
        values = dict(values)
        camera = values.get("camera") or {}
        rate = float(camera.rate_hz if isinstance(camera, CameraSpec)
                     else camera.get("rate_hz", CameraSpec.model_fields["rate_hz"].default))
        if values.get("groundtruth_hz") is None and rate > 0:
            values["groundtruth_hz"] = rate * math.ceil(100.0 / rate - 1e-9)
        gt = values.get("groundtruth_hz")
        if values.get("dt_s") is None and isinstance(gt, (int, float)) and gt > 0:
            values["dt_s"] = 1.0 / (gt * math.ceil(1.0 / (gt * 0.002) - 1e-9))
        return values

    @model_validator(mode="after")
    def _can_be(self) -> Scenario:
        check_can_be(self)
        return self

    @property
    def rest(self) -> np.ndarray:
        """The object's rest position, shape (3,), metres, world."""
        return np.array([0.0, 0.0, self.object.rest_height_m])

    def shoulder(self) -> np.ndarray:
        """The arm's shoulder (our Bravo-7-like model), shape (3,), metres, world."""
        yaw = self.mount_yaw()
        c, sn = math.cos(yaw), math.sin(yaw)
        R = np.array([[c, -sn, 0.0], [sn, c, 0.0], [0.0, 0.0, 1.0]])
        return np.asarray(self.mount.position) + R @ default_arm().shoulder

    def mount_yaw(self) -> float:
        """The mount's yaw about z, radians: facing the object's rest, plus the offset."""
        to_object = self.rest - np.asarray(self.mount.position)
        return float(np.arctan2(to_object[1], to_object[0])) + math.radians(
            self.mount.yaw_offset_deg)


def check_can_be(s: Scenario) -> None:
    """Refuse a scenario that cannot be, naming what is wrong (ValueError)."""
    depth, obj = s.sea.depth_m, s.object
    if obj.rest_height_m + obj.bounding_radius_m > depth:
        raise ValueError(f"object.rest_height_m: the object ({obj.rest_height_m:g} m up, "
                         f"{obj.bounding_radius_m:.3g} m about its centroid) is not under "
                         f"water {depth:g} m deep")
    if obj.rest_height_m - obj.bounding_radius_m <= 0.02:
        raise ValueError("object.rest_height_m: the object would lie on the seabed")
    mount = np.asarray(s.mount.position)
    if not 0 < mount[2] < depth:
        raise ValueError(f"mount.position: z = {mount[2]:g} m is out of the water (seabed 0, "
                         f"surface {depth:g} m)")
    eye = np.asarray(s.camera.eye)
    if not 0 < eye[2] < depth:
        raise ValueError(f"camera.eye: z = {eye[2]:g} m is out of the water (seabed 0, "
                         f"surface {depth:g} m)")
    if np.linalg.norm(eye - s.rest) <= obj.bounding_radius_m + 0.05:
        raise ValueError("camera.eye: inside or touching the object")
    if np.linalg.norm(np.asarray(s.camera.target) - eye) < 1e-6:
        raise ValueError("camera.target: the same point as camera.eye")
    if np.linalg.norm(mount - s.rest) <= obj.bounding_radius_m + 0.05:
        raise ValueError("mount.position: inside or touching the object")
    ratio = s.groundtruth_hz / s.camera.rate_hz
    if s.groundtruth_hz * s.dt_s > 1 or ratio < 1 or abs(ratio - round(ratio)) > 1e-9:
        raise ValueError("camera.rate_hz: must divide groundtruth_hz, and dt_s <= "
                         "1/groundtruth_hz")
    reach = arm_reach_problem(s)
    if reach:
        raise ValueError(f"mount.position: {reach}")


def arm_reach_problem(s: Scenario) -> str | None:
    """Why the arm (our Bravo-7-like model) cannot reach the object's rest position, if so."""
    arm = default_arm()
    distance = float(np.linalg.norm(s.rest - s.shoulder()))
    if distance > arm.reach_m:
        return (f"the object's rest position is {distance:.3f} m from the arm's shoulder, "
                f"beyond its {arm.reach_m:.3f} m reach")
    return None


@functools.cache
def default_arm() -> ArmModel:
    """Our Bravo-7-like arm, read once per process."""
    return ArmModel.load()


def paper_scenario(wave: int, object_name: str, **overrides: object) -> Scenario:
    """The paper's configuration: Table I's wave ``wave`` (1-3) and one of its four objects
    in our model of the tank (mount beside the camera, facing the object)."""
    if wave not in TABLE_I:
        raise ValueError(f"wave must be one of {sorted(TABLE_I)}, got {wave}")
    if object_name not in OBJECTS:
        raise ValueError(f"object must be one of {sorted(OBJECTS)}, got {object_name!r}")
    cond = TABLE_I[wave]
    fields: dict[str, object] = {
        "name": f"paper-w{wave}-{object_name}",
        "sea": SeaSpec(height_m=cond.height_m, period_s=cond.period_s),
        "object": ObjectModel.named(object_name), **overrides}
    return Scenario(**fields)


NAMED: dict[str, tuple[int, str]] = {
    f"paper-w{w}-{o}": (w, o) for w in sorted(TABLE_I) for o in sorted(OBJECTS)}


def load_scenario(source: str | Path) -> Scenario:
    """A named scenario (``paper-w1-buoy``...) or a YAML/JSON file; raises ValueError with one
    line naming the file and what is wrong."""
    text = str(source)
    if text in NAMED:
        return paper_scenario(*NAMED[text])
    path = Path(source)
    try:
        doc = yaml.safe_load(path.read_text())
    except (OSError, yaml.YAMLError) as exc:
        raise ValueError(f"{path}: cannot read a scenario: {exc}") from None
    if not isinstance(doc, dict):
        raise ValueError(f"{path}: a scenario is a mapping (sea, object, mount, camera...)")
    try:
        return Scenario(**doc)
    except ValidationError as exc:
        raise ValueError(f"{path}: {describe(exc)}") from None
    except ValueError as exc:
        raise ValueError(f"{path}: {exc}") from None


def describe(exc: ValidationError) -> str:
    """A scenario's first problem in one line: ``field.path: what is wrong``."""
    err = exc.errors()[0]
    where = ".".join(str(p) for p in err["loc"])
    msg = err["msg"].removeprefix("Value error, ")
    return f"{where}: {msg}" if where else msg

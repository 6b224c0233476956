"""``wavegrasp record``: a wave-tank recording made from physics, per the recording contract.

The tank (frame ``world``: origin on the seabed at the tether anchor, z up, x along the waves):
water 0.93 m deep; the object's centroid 0.525 m above the floor (0.405 m below still water)
while its tether is vertical. At that depth linear theory reproduces rows 1 and 2 of the paper's
Table I within 6 % (see recordings/README.md). The Trisect-like camera looks at the object from
1 m across the tank, slightly from above; the arm's mount ``bravo_base_link`` sits beside the
camera, facing the object.
"""

from __future__ import annotations

import argparse
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation
from tqdm import tqdm

from wavegrasp.recording_io.writer import RecordingWriter
from wavegrasp.wavetank.body import OBJECTS, ObjectSpec, TetheredBody
from wavegrasp.wavetank.camera import (
    Mesh,
    TrisectCamera,
    cylinder_mesh,
    look_at,
    object_mesh,
    seabed_mesh,
    transform,
)
from wavegrasp.wavetank.scenario import (
    NAMED,
    PAPER_CAMERA_EYE,
    TANK_REST_HEIGHT_M,
    CameraSpec,
    ObjectModel,
    Scenario,
    load_scenario,
    paper_scenario,
)
from wavegrasp.wavetank.waves import TABLE_I, WaveCondition, jonswap_sea, regular_sea

GENERATOR_VERSION = "1"
ANCHOR = np.zeros(3)
TETHER_RADIUS_M = 0.002
T0_NS = 1_700_000_000 * 10**9  # recordings start at a fixed epoch: same seed, same bytes


@dataclass(frozen=True)
class RecordConfig:
    """What to generate. Times seconds, rates Hz, offsets metres."""

    wave: int
    object: str
    seconds: float
    seed: int = 0
    irregular: bool = False
    rate_hz: float = 10.0
    groundtruth_hz: float = 100.0
    object_scale: float = 1.0
    camera_offset: tuple[float, float, float] = (0.0, 0.0, 0.0)
    preroll_s: float = 30.0
    dt_s: float = 0.002
    camera: dict = field(default_factory=dict)  # TrisectCamera overrides (width, noise...)

    def __post_init__(self) -> None:
        # 40 and 40.0 seconds are the same recording (and the same cache entry).
        for name in ("seconds", "rate_hz", "groundtruth_hz", "object_scale", "preroll_s", "dt_s"):
            object.__setattr__(self, name, float(getattr(self, name)))
        object.__setattr__(self, "camera_offset", tuple(float(v) for v in self.camera_offset))

    def check(self) -> None:
        if self.wave not in TABLE_I:
            raise ValueError(f"wave must be one of {sorted(TABLE_I)}, got {self.wave}")
        if self.object not in OBJECTS:
            raise ValueError(f"object must be one of {sorted(OBJECTS)}, got {self.object!r}")
        for name in ("seconds", "rate_hz", "groundtruth_hz", "dt_s"):
            if not getattr(self, name) > 0:
                raise ValueError(f"{name} must be positive, got {getattr(self, name)}")
        ratio = self.groundtruth_hz / self.rate_hz
        if self.groundtruth_hz * self.dt_s > 1 or ratio < 1 or abs(ratio - round(ratio)) > 1e-9:
            raise ValueError("need dt_s <= 1/groundtruth_hz, and rate_hz dividing groundtruth_hz")

    def to_scenario(self) -> Scenario:
        """The paper's configuration with this config's changes, as a scenario."""
        self.check()
        obj = ObjectModel.named(self.object)
        if self.object_scale != 1:
            f = self.object_scale
            base = OBJECTS[self.object]
            obj = obj.model_copy(update={
                "diameter_m": obj.diameter_m * f, "mass_kg": obj.mass_kg * f**3,
                "length_m": obj.length_m * f if obj.length_m is not None else None,
                # the tether keeps its length: the centroid moves by the attachment's offset
                "rest_height_m": TANK_REST_HEIGHT_M + base.attach_offset * (f - 1),
                "name": f"{self.object}x{f:g}"})
        eye = tuple(float(v) for v in np.add(PAPER_CAMERA_EYE, self.camera_offset))
        camera = CameraSpec(eye=eye, rate_hz=self.rate_hz, **self.camera)
        sea = paper_scenario(self.wave, self.object).sea
        if self.irregular:
            sea = sea.model_copy(update={"kind": "jonswap"})
        return Scenario(name=f"paper-w{self.wave}-{self.object}", sea=sea, object=obj,
                        camera=camera, seconds=self.seconds, seed=self.seed,
                        preroll_s=self.preroll_s, groundtruth_hz=self.groundtruth_hz,
                        dt_s=self.dt_s)


def arm_mount(scenario: Scenario) -> tuple[np.ndarray, np.ndarray]:
    """``bravo_base_link`` in world: position and quaternion (x, y, z, w)."""
    yaw = scenario.mount_yaw()
    return np.asarray(scenario.mount.position), Rotation.from_euler("z", yaw).as_quat(
        canonical=True)


def pose_matrix(position: np.ndarray, quat_xyzw: np.ndarray) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = Rotation.from_quat(quat_xyzw).as_matrix()
    T[:3, 3] = position
    return T


@dataclass(frozen=True)
class Trajectory:
    """The object's ground truth at ``groundtruth_hz``.

    times_s : array, shape (n,), seconds from the start; positions : array, shape (n, 3),
    metres, world (volume centroid); quats : array, shape (n, 4), (x, y, z, w), body z along
    the tether; slack_fraction : share of physics steps with a slack tether.
    """

    times_s: np.ndarray
    positions: np.ndarray
    quats: np.ndarray
    slack_fraction: float
    spec: ObjectSpec
    tether_length: float


def as_scenario(what: RecordConfig | Scenario) -> Scenario:
    return what if isinstance(what, Scenario) else what.to_scenario()


def simulate(what: RecordConfig | Scenario) -> Trajectory:
    """Run the tank's physics (after ``preroll_s`` for transients to die out)."""
    s = as_scenario(what)
    sea_rng = np.random.default_rng(s.seed).spawn(2)[0]
    cond = WaveCondition(0, s.sea.height_m, s.sea.period_s, 0.0, 0.0)
    make_sea = jonswap_sea if s.sea.kind == "jonswap" else regular_sea
    sea = make_sea(cond, s.sea.depth_m, sea_rng, current=(s.sea.current_mps, s.sea.current_deg))
    spec = s.object.spec()
    body = TetheredBody(spec, sea, ANCHOR, s.object.rest_height_m - spec.attach_offset)
    t = -s.preroll_s
    while t < 0:
        body.step(t, s.dt_s)
        t += s.dt_s
    body.slack_steps = body.steps = 0
    every = int(round(1 / (s.groundtruth_hz * s.dt_s)))
    n = int(round(s.seconds * s.groundtruth_hz))
    pos, quat = np.empty((n, 3)), np.empty((n, 4))
    for i in range(n * every):
        if i % every == 0:
            pos[i // every], quat[i // every] = body.p, body.orientation()
        body.step(i * s.dt_s, s.dt_s)
    return Trajectory(np.arange(n) / s.groundtruth_hz, pos, quat, body.slack_fraction, spec,
                      body.tether_length)


def scene(traj: Trajectory, i: int, shape: Mesh, seabed: Mesh) -> list[Mesh]:
    """World-frame meshes at sample ``i``: the object, its tether, the seabed."""
    p, q = traj.positions[i], traj.quats[i]
    axis = p - ANCHOR
    tether_end = p - traj.spec.attach_offset * axis / np.linalg.norm(axis)
    length = float(np.linalg.norm(tether_end - ANCHOR))
    tether = cylinder_mesh(TETHER_RADIUS_M, length, 12)
    return [transform(shape, pose_matrix(p, q)),
            transform(tether, pose_matrix((ANCHOR + tether_end) / 2, q)), seabed]


def generate(what: RecordConfig | Scenario, out: Path,
             progress: bool = False) -> dict[str, float]:
    """Write the recording to ``out``; returns facts about it (slack fraction, timing...)."""
    started = time.perf_counter()
    s = as_scenario(what)
    traj = simulate(s)
    cam_rng = np.random.default_rng(s.seed).spawn(2)[1]
    eye = np.asarray(s.camera.eye, dtype=float)
    T_cam = look_at(eye, np.asarray(s.camera.target, dtype=float))
    camera = TrisectCamera(T_world_optical=T_cam, **s.camera.sensor())
    spec = traj.spec
    shape = object_mesh(spec)
    seabed = seabed_mesh(4.0, 4.0)
    arm_pos, arm_q = arm_mount(s)
    cam_q = Rotation.from_matrix(T_cam[:3, :3]).as_quat(canonical=True)
    tfs = [("world", "trisect_optical", eye, cam_q), ("world", "bravo_base_link", arm_pos, arm_q)]
    frame_every = int(round(s.groundtruth_hz / s.camera.rate_hz))
    tf_every = int(round(s.groundtruth_hz))
    wave, object_name = NAMED.get(s.name, ("", spec.name))
    meta = {"generator": "wavegrasp.wavetank", "generator_version": GENERATOR_VERSION,
            "wave": str(wave), "object": object_name, "seed": str(s.seed),
            "sea": s.sea.kind, "seconds": f"{s.seconds:g}",
            "water_depth_m": f"{s.sea.depth_m}", "tether_length_m": f"{traj.tether_length:.4f}",
            "object_scale": f"{spec.radius / OBJECTS[object_name].radius:g}"
            if object_name in OBJECTS else "1", "object_radius_m": f"{spec.radius:g}",
            "object_length_m": f"{spec.length:g}", "object_shape": spec.shape,
            "camera_eye": " ".join(f"{v:g}" for v in eye),
            "scenario": s.model_dump_json()}
    points = []
    with RecordingWriter(out, meta) as w:
        for i in tqdm(range(len(traj.times_s)), disable=not progress, file=sys.stderr,
                      unit="sample", desc="recording"):
            stamp = T0_NS + int(round(traj.times_s[i] * 1e9))
            if i % tf_every == 0:
                w.write_tf_static(stamp, tfs)
            w.write_groundtruth(stamp, traj.positions[i], traj.quats[i])
            if i % frame_every == 0:
                cloud = camera.capture(scene(traj, i, shape, seabed), cam_rng)
                if s.camera.cloud == "organized":
                    w.write_organized_points(stamp, camera.organize(cloud), camera.height,
                                             camera.width)
                else:
                    w.write_points(stamp, cloud)
                points.append(len(cloud))
        facts = {"slack_fraction": traj.slack_fraction, "frames": len(points),
                 "points_per_frame": float(np.mean(points))}
        w.add_metadata("wavegrasp.generation", {k: f"{v:.6g}" for k, v in facts.items()})
    return {**facts, "generation_s": time.perf_counter() - started}


def parse_args(argv: list[str] | None) -> tuple[Scenario, Path]:
    """The scenario to record and where; raises ValueError naming what is wrong."""
    p = argparse.ArgumentParser(prog="wavegrasp record", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--scenario", help="a scenario file (YAML or JSON) or a named scenario "
                   f"({', '.join(list(NAMED)[:2])}, ...); other options then override its own")
    p.add_argument("--wave", type=int, choices=sorted(TABLE_I))
    p.add_argument("--object", choices=sorted(OBJECTS))
    p.add_argument("--seconds", type=float)
    p.add_argument("--seed", type=int)
    p.add_argument("--out", type=Path, required=True)
    p.add_argument("--irregular", action="store_true", help="JONSWAP sea with the same Hs/Tp")
    p.add_argument("--rate", type=float, help="camera frames per second (default 10)")
    p.add_argument("--object-scale", type=float, default=1.0, help="object size factor")
    p.add_argument("--camera-offset", type=float, nargs=3, default=(0.0, 0.0, 0.0),
                   metavar=("DX", "DY", "DZ"), help="move the camera, metres in world")
    p.add_argument("--width", type=int, help="camera pixels across (default 320)")
    p.add_argument("--height", type=int, help="camera pixels down (default 240)")
    a = p.parse_args(argv)
    if a.scenario:
        if a.wave or a.object or a.irregular or a.object_scale != 1 or any(a.camera_offset):
            p.error("--scenario describes the sea, object and camera: drop --wave, --object, "
                    "--irregular, --object-scale and --camera-offset")
        scenario = load_scenario(a.scenario)
    else:
        if a.wave is None or a.object is None or a.seconds is None:
            p.error("give --scenario, or --wave, --object and --seconds")
        camera = {k: v for k, v in (("width", a.width), ("height", a.height)) if v is not None}
        scenario = RecordConfig(wave=a.wave, object=a.object, seconds=a.seconds,
                                seed=a.seed or 0, irregular=a.irregular,
                                rate_hz=a.rate or 10.0, object_scale=a.object_scale,
                                camera_offset=tuple(a.camera_offset),
                                camera=camera).to_scenario()
    camera_changes = {k: v for k, v in (("rate_hz", a.rate), ("width", a.width),
                                         ("height", a.height)) if v is not None}
    changes = {k: v for k, v in (("seconds", a.seconds), ("seed", a.seed)) if v is not None}
    if camera_changes:
        changes["camera"] = scenario.camera.model_copy(update=camera_changes)
    if changes:  # validated again as a whole
        scenario = Scenario(**{**dict(scenario), **changes})
    return scenario, a.out


def main(argv: list[str] | None = None) -> int:
    try:
        scenario, out = parse_args(argv)
        out.parent.mkdir(parents=True, exist_ok=True)
        facts = generate(scenario, out, progress=True)
    except (ValueError, OSError) as exc:
        print(f"wavegrasp record: {exc}", file=sys.stderr)
        return 2
    print(f"wrote {out}: {facts['frames']} frames, {facts['points_per_frame']:.0f} points a "
          f"frame, {scenario.seconds / facts['generation_s']:.1f}x real time", file=sys.stderr)
    warning = slack_warning(scenario.object.name, facts["slack_fraction"])
    if warning:
        print(f"warning: {warning}", file=sys.stderr)
    return 0


def slack_warning(name: str, slack_fraction: float) -> str | None:
    """What to tell the user when the tether went slack for more than 1 % of the time."""
    if slack_fraction <= 0.01:
        return None
    return (f"the tether was slack {slack_fraction:.0%} of the time: the {name} is not "
            "buoyant enough to keep it taut, so its centroid leaves the tether's sphere")

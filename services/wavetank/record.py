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
    seabed_mesh,
    sphere_mesh,
    transform,
)
from wavegrasp.wavetank.waves import TABLE_I, jonswap_sea, regular_sea

GENERATOR_VERSION = "1"
DEPTH_M = 0.93
CENTROID_HEIGHT_M = 0.525
ANCHOR = np.zeros(3)
CAMERA_EYE = np.array([0.0, -1.0, 0.75])
CAMERA_TARGET = np.array([0.0, 0.0, 0.5])
ARM_BASE = np.array([0.30, -0.60, 0.40])
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


def arm_mount() -> tuple[np.ndarray, np.ndarray]:
    """``bravo_base_link`` in world: position and quaternion (x, y, z, w), x towards the object."""
    to_object = np.array([0.0, 0.0, CENTROID_HEIGHT_M]) - ARM_BASE
    yaw = np.arctan2(to_object[1], to_object[0])
    return ARM_BASE, Rotation.from_euler("z", yaw).as_quat(canonical=True)


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


def object_spec(cfg: RecordConfig) -> ObjectSpec:
    spec = OBJECTS[cfg.object]
    return spec.scaled(cfg.object_scale) if cfg.object_scale != 1 else spec


def simulate(cfg: RecordConfig) -> Trajectory:
    """Run the tank's physics for ``cfg`` (after ``preroll_s`` for transients to die out)."""
    cfg.check()
    sea_rng = np.random.default_rng(cfg.seed).spawn(2)[0]
    cond = TABLE_I[cfg.wave]
    sea = (jonswap_sea if cfg.irregular else regular_sea)(cond, DEPTH_M, sea_rng)
    spec = object_spec(cfg)
    body = TetheredBody(spec, sea, ANCHOR, CENTROID_HEIGHT_M - OBJECTS[cfg.object].attach_offset)
    t = -cfg.preroll_s
    while t < 0:
        body.step(t, cfg.dt_s)
        t += cfg.dt_s
    body.slack_steps = body.steps = 0
    every = int(round(1 / (cfg.groundtruth_hz * cfg.dt_s)))
    n = int(round(cfg.seconds * cfg.groundtruth_hz))
    pos, quat = np.empty((n, 3)), np.empty((n, 4))
    for i in range(n * every):
        if i % every == 0:
            pos[i // every], quat[i // every] = body.p, body.orientation()
        body.step(i * cfg.dt_s, cfg.dt_s)
    return Trajectory(np.arange(n) / cfg.groundtruth_hz, pos, quat, body.slack_fraction, spec,
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


def generate(cfg: RecordConfig, out: Path, progress: bool = False) -> dict[str, float]:
    """Write the recording to ``out``; returns facts about it (slack fraction, timing...)."""
    started = time.perf_counter()
    traj = simulate(cfg)
    cam_rng = np.random.default_rng(cfg.seed).spawn(2)[1]
    eye = CAMERA_EYE + np.asarray(cfg.camera_offset, dtype=float)
    T_cam = look_at(eye, CAMERA_TARGET)
    camera = TrisectCamera(T_world_optical=T_cam, **cfg.camera)
    spec = traj.spec
    shape = sphere_mesh(spec.radius) if spec.shape == "sphere" else cylinder_mesh(
        spec.radius, spec.length)
    seabed = seabed_mesh(4.0, 4.0)
    arm_pos, arm_q = arm_mount()
    cam_q = Rotation.from_matrix(T_cam[:3, :3]).as_quat(canonical=True)
    tfs = [("world", "trisect_optical", eye, cam_q), ("world", "bravo_base_link", arm_pos, arm_q)]
    frame_every = int(round(cfg.groundtruth_hz / cfg.rate_hz))
    tf_every = int(round(cfg.groundtruth_hz))
    meta = {"generator": "wavegrasp.wavetank", "generator_version": GENERATOR_VERSION,
            "wave": str(cfg.wave), "object": cfg.object, "seed": str(cfg.seed),
            "sea": "jonswap" if cfg.irregular else "regular", "seconds": f"{cfg.seconds:g}",
            "water_depth_m": f"{DEPTH_M}", "tether_length_m": f"{traj.tether_length:.4f}",
            "object_scale": f"{cfg.object_scale:g}", "object_radius_m": f"{spec.radius:g}",
            "object_length_m": f"{spec.length:g}", "object_shape": spec.shape,
            "camera_eye": " ".join(f"{v:g}" for v in eye)}
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
                w.write_points(stamp, cloud)
                points.append(len(cloud))
        facts = {"slack_fraction": traj.slack_fraction, "frames": len(points),
                 "points_per_frame": float(np.mean(points))}
        w.add_metadata("wavegrasp.generation", {k: f"{v:.6g}" for k, v in facts.items()})
    return {**facts, "generation_s": time.perf_counter() - started}


def parse_args(argv: list[str] | None) -> RecordConfig | tuple[RecordConfig, Path]:
    p = argparse.ArgumentParser(prog="wavegrasp record", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--wave", type=int, required=True, choices=sorted(TABLE_I))
    p.add_argument("--object", required=True, choices=sorted(OBJECTS))
    p.add_argument("--seconds", type=float, required=True)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", type=Path, required=True)
    p.add_argument("--irregular", action="store_true", help="JONSWAP sea with the same Hs/Tp")
    p.add_argument("--rate", type=float, default=10.0, help="camera frames per second")
    p.add_argument("--object-scale", type=float, default=1.0, help="object size factor")
    p.add_argument("--camera-offset", type=float, nargs=3, default=(0.0, 0.0, 0.0),
                   metavar=("DX", "DY", "DZ"), help="move the camera, metres in world")
    p.add_argument("--width", type=int, default=320, help="camera pixels across")
    p.add_argument("--height", type=int, default=240, help="camera pixels down")
    a = p.parse_args(argv)
    cfg = RecordConfig(wave=a.wave, object=a.object, seconds=a.seconds, seed=a.seed,
                       irregular=a.irregular, rate_hz=a.rate, object_scale=a.object_scale,
                       camera_offset=tuple(a.camera_offset),
                       camera={"width": a.width, "height": a.height})
    return cfg, a.out


def main(argv: list[str] | None = None) -> int:
    cfg, out = parse_args(argv)
    try:
        out.parent.mkdir(parents=True, exist_ok=True)
        facts = generate(cfg, out, progress=True)
    except (ValueError, OSError) as exc:
        print(f"wavegrasp record: {exc}", file=sys.stderr)
        return 2
    print(f"wrote {out}: {facts['frames']} frames, {facts['points_per_frame']:.0f} points a "
          f"frame, {cfg.seconds / facts['generation_s']:.1f}x real time", file=sys.stderr)
    warning = slack_warning(cfg.object, facts["slack_fraction"])
    if warning:
        print(f"warning: {warning}", file=sys.stderr)
    return 0


def slack_warning(name: str, slack_fraction: float) -> str | None:
    """What to tell the user when the tether went slack for more than 1 % of the time."""
    if slack_fraction <= 0.01:
        return None
    return (f"the tether was slack {slack_fraction:.0%} of the time: the {name} is not "
            "buoyant enough to keep it taut, so its centroid leaves the tether's sphere")

"""A quick kinematic (not physics) synthetic recording: a tethered sphere swinging in waves.

Scene, in `world` (tank frame, z up, metres): a sphere of radius 0.05 whose centre is 0.6 m from
a seabed anchor at the origin (a buoy on a taut tether), swinging harmonically (period 1.25 s,
6 degrees, along x) plus a slow sway (period 9 s, 2 degrees, along y). The camera
`trisect_optical` sits at (-0.95, 0, 0.9) looking at (0, 0, 0.6), about 1 m away (z forward,
x right, y down); the arm base `bravo_base_link` is at (-0.75, 0.25, 0.5), axes as world's.
Each cloud: half the points on the camera-facing part of the sphere, 0.5 % outliers, the rest on
the seabed (z = 0) in view and not hidden by the sphere; 2 mm Gaussian noise. Stamps start at
T0_NS; ground truth at 100 Hz, tf_static every second from the start.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation
from tqdm import tqdm

from .writer import RecordingWriter

T0_NS = 1_700_000_000 * 10**9  # fixed start, so that files are byte-identical per seed
TETHER, RADIUS, PERIOD, NOISE = 0.6, 0.05, 1.25, 0.002
EYE, TARGET, ARM_BASE = np.array([-0.95, 0.0, 0.9]), np.array([0.0, 0.0, 0.6]), (-0.75, 0.25, 0.5)
TAN_HALF_FOV = np.array([0.7, 0.55])  # x, y


def camera_axes() -> np.ndarray:
    """Return R, shape (3, 3): columns are trisect_optical's x, y, z axes in world."""
    z = (TARGET - EYE) / np.linalg.norm(TARGET - EYE)
    x = np.cross(z, [0.0, 0.0, 1.0])
    x /= np.linalg.norm(x)
    return np.column_stack([x, np.cross(z, x), z])


def object_pose(t: float) -> tuple[np.ndarray, np.ndarray]:
    """Return the sphere's centre, shape (3,), metres in world, and quaternion xyzw at `t` s."""
    a = np.radians(6.0) * np.sin(2 * np.pi * t / PERIOD)
    b = np.radians(2.0) * np.sin(2 * np.pi * t / 9.0 + 0.7)
    centre = TETHER * np.array([np.sin(a) * np.cos(b), np.sin(b), np.cos(a) * np.cos(b)])
    return centre, Rotation.from_euler("YX", [a, -b]).as_quat(canonical=True)


def cloud(rng: np.random.Generator, centre: np.ndarray, n: int, rot: np.ndarray) -> np.ndarray:
    """Return a noisy cloud, shape (<= n, 3), float32, metres in trisect_optical."""
    n_out, n_obj = max(1, n // 200), n // 2
    n_bed = n - n_obj - n_out
    u = rng.normal(size=(4 * n_obj, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    surf = centre + RADIUS * u
    obj = surf[np.einsum("ij,ij->i", u, EYE - surf) > 0][:n_obj]
    bed = np.column_stack([rng.uniform(-0.3, 1.0, 4 * n_bed), rng.uniform(-0.6, 0.6, 4 * n_bed),
                           np.zeros(4 * n_bed)])
    ray, to_c = bed - EYE, centre - EYE
    s = np.clip(ray @ to_c / np.einsum("ij,ij->i", ray, ray), 0.0, 1.0)
    hidden = np.linalg.norm(to_c - s[:, None] * ray, axis=1) < RADIUS
    cam = np.vstack([obj, bed[~hidden]]) - EYE
    cam = cam @ rot  # world offsets -> trisect_optical coordinates
    seen = (cam[:, 2] > 0) & (np.abs(cam[:, :2]) < TAN_HALF_FOV * cam[:, 2:]).all(axis=1)
    cam = cam[seen][: n - n_out]
    cam += rng.normal(scale=NOISE, size=cam.shape)
    out = rng.uniform([-0.5, -0.4, 0.3], [0.5, 0.4, 1.8], size=(n_out, 3))
    return np.vstack([cam, out]).astype(np.float32)


def write_synthetic_recording(
    path: str | Path, seconds: float = 10.0, rate_hz: float = 10.0,
    points_per_frame: int = 3000, seed: int = 0, progress: bool = False,
) -> Path:
    """Write the scene above as an MCAP recording (same arguments, same bytes); return its path.

    `rate_hz` is the point-cloud rate; `points_per_frame` the points per cloud (n, 3).
    """
    rng, rot = np.random.default_rng(seed), camera_axes()
    cam_q = Rotation.from_matrix(rot).as_quat(canonical=True)
    tfs = [("world", "trisect_optical", EYE, cam_q), ("world", "bravo_base_link", ARM_BASE,
                                                       (0.0, 0.0, 0.0, 1.0))]
    events = sorted(
        [(k * 10**9, 0) for k in range(int(np.ceil(seconds)))]
        + [(k * 10**7, 1) for k in range(int(round(seconds * 100)))]
        + [(round(k * 1e9 / rate_hz), 2) for k in range(int(round(seconds * rate_hz)))]
    )
    meta = {"generator": "wavegrasp.synthetic", "generator_version": "1", "seed": str(seed),
            "wave": "kinematic", "object": "sphere"}
    with RecordingWriter(path, meta) as w:
        for dt, kind in tqdm(events, disable=not progress, file=sys.stderr, unit="msg"):
            centre, quat = object_pose(dt * 1e-9)
            if kind == 0:
                w.write_tf_static(T0_NS + dt, tfs)
            elif kind == 1:
                w.write_groundtruth(T0_NS + dt, centre, quat)
            else:
                w.write_points(T0_NS + dt, cloud(rng, centre, points_per_frame, rot))
    return Path(path)


def main(argv: list[str] | None = None) -> int:
    """Command line: ``python -m wavegrasp.recording_io.synthetic --out FILE [...]``."""
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--seconds", type=float, default=10.0)
    p.add_argument("--rate", type=float, default=10.0, help="point clouds per second")
    p.add_argument("--points", type=int, default=3000, help="points per cloud")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", required=True, type=Path)
    a = p.parse_args(argv)
    print(write_synthetic_recording(a.out, a.seconds, a.rate, a.points, a.seed, progress=True))
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""Mesh accumulation from simulated one-sided noisy stereo clouds of a swinging object."""

from __future__ import annotations

import base64
import time
from pathlib import Path

import numpy as np
import open3d as o3d
import pytest
from scipy.spatial.transform import Rotation

from wavegrasp.perception.mesh import (
    MeshAccumulator,
    build_mesh,
    mesh_volume,
    write_obj,
)
from wavegrasp.schemas.mesh_codec import decode_mesh, encode_mesh

CAMERA = np.array([-1.0, 0.0, 0.3])  # metres, world; the object swings around the origin
SHAPES = {  # name: (radius m, length m or None for a sphere)
    "sphere": (0.06, None),
    "can": (0.033, 0.122),
    "bottle": (0.032, 0.160),
}


def true_volume(radius: float, length: float | None) -> float:
    return 4 / 3 * np.pi * radius**3 if length is None else np.pi * radius**2 * length


def sample_surface(rng: np.random.Generator, radius: float, length: float | None,
                   n: int) -> tuple[np.ndarray, np.ndarray]:
    """Uniform points and outward normals on the true surface, shape (n, 3), frame object."""
    if length is None:
        u = rng.normal(size=(n, 3))
        u /= np.linalg.norm(u, axis=1, keepdims=True)
        return radius * u, u
    side, cap = 2 * np.pi * radius * length, np.pi * radius**2
    kind = rng.choice(3, size=n, p=np.array([side, cap, cap]) / (side + 2 * cap))
    phi, z = rng.uniform(0, 2 * np.pi, n), rng.uniform(-length / 2, length / 2, n)
    r = radius * np.sqrt(rng.uniform(0, 1, n))
    sign = np.where(kind == 1, 1.0, -1.0)
    pts = np.where((kind == 0)[:, None],
                   np.c_[radius * np.cos(phi), radius * np.sin(phi), z],
                   np.c_[r * np.cos(phi), r * np.sin(phi), sign * length / 2])
    nrm = np.where((kind == 0)[:, None], np.c_[np.cos(phi), np.sin(phi), 0 * phi],
                   np.c_[0 * phi, 0 * phi, sign])
    return pts, nrm


def simulate(shape: str, frames: int = 100, seed: int = 0, centre_sigma: float = 0.001,
             axis_sigma_deg: float = 1.0) -> tuple[MeshAccumulator, float]:
    """10 Hz frames of the object swinging ±15° and moving ±10 cm, seen from CAMERA, depth
    noise 1.5 mm along the ray; the accumulator gets the true pose with errors like the
    fitter's (centre: `centre_sigma` metres per axis; axis: `axis_sigma_deg` per tilt axis).
    Returns the accumulator and the mean time (s) of one `add`."""
    rng = np.random.default_rng(seed)
    radius, length = SHAPES[shape]
    acc, spent = MeshAccumulator(), 0.0
    for k in range(frames):
        t = k / 10.0
        swing = np.deg2rad(15) * np.sin(2 * np.pi * t / 3.1)
        R = Rotation.from_rotvec(swing * np.array([0.6, 0.8, 0.0])).as_matrix()
        centre = 0.1 * np.array([np.sin(2 * np.pi * t / 3.1), 0.5 * np.sin(t), 0.3 * np.cos(t)])
        p, n = sample_surface(rng, radius, length, 1100)
        p, n = p @ R.T + centre, n @ R.T
        visible = np.sum(n * (CAMERA - p), axis=1) > 0  # convex: back-face culling = visibility
        p = p[visible]
        ray = (p - CAMERA) / np.linalg.norm(p - CAMERA, axis=1, keepdims=True)
        p = p + rng.normal(0, 0.0015, (len(p), 1)) * ray
        tilt = rng.normal(0, np.deg2rad(axis_sigma_deg), 2)
        R_fit = R @ Rotation.from_rotvec([tilt[0], tilt[1], 0]).as_matrix()
        if length is None:
            R_fit = np.eye(3)  # a sphere's fitted frame is world-aligned
        c_fit = centre + rng.normal(0, centre_sigma, 3)
        t0 = time.perf_counter()
        acc.add(p, c_fit, R_fit)
        spent += time.perf_counter() - t0
    return acc, spent / frames


@pytest.fixture(scope="module")
def meshes() -> dict[str, tuple[np.ndarray, np.ndarray, float, float]]:
    out = {}
    for shape in SHAPES:
        acc, per_frame = simulate(shape)
        t0 = time.perf_counter()
        v, t = build_mesh(acc.points_object(), weights=acc.counts())
        out[shape] = (v, t, per_frame, time.perf_counter() - t0)
    return out


@pytest.mark.parametrize("shape", list(SHAPES))
def test_volume_from_ten_seconds_of_frames(meshes: dict, shape: str) -> None:
    v, t, per_frame, build_s = meshes[shape]
    volume, truth = mesh_volume(v, t), true_volume(*SHAPES[shape])
    print(f"{shape}: volume error {100 * (volume / truth - 1):+.2f} %, add {per_frame * 1e3:.3f}"
          f" ms/frame, build_mesh {build_s * 1e3:.0f} ms, {len(v)} vertices {len(t)} triangles")
    assert abs(volume / truth - 1) < 0.03  # brief: 15 %, ideally 5 %; measured within 1.5 %
    # Speed is for the benchmark (python -m wavegrasp.ops.bench_perception), not a test.


@pytest.mark.parametrize("shape", list(SHAPES))
def test_mesh_is_closed_and_outward(meshes: dict, shape: str) -> None:
    v, t = meshes[shape][:2]
    assert v.dtype == np.float32 and t.dtype == np.int32
    m = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(v.astype(float)),
                                  o3d.utility.Vector3iVector(t))
    assert m.is_watertight() and m.is_orientable()
    assert mesh_volume(v, t) > 0
    assert np.isclose(m.get_volume(), mesh_volume(v, t), rtol=1e-5)


def test_symmetric_completion_matters() -> None:
    acc, _ = simulate("can", frames=20)
    full = mesh_volume(*build_mesh(acc.points_object(), weights=acc.counts()))
    half = mesh_volume(*build_mesh(acc.points_object(), symmetric=False, weights=acc.counts()))
    assert 0.3 < half / full < 0.85


def test_accumulator_memory_is_bounded() -> None:
    acc = MeshAccumulator(voxel_m=0.003, max_points=500)
    rng = np.random.default_rng(1)
    for _ in range(5):
        acc.add(rng.uniform(-0.1, 0.1, (400, 3)), np.zeros(3), np.eye(3))
    assert acc.frames == 5 and len(acc.points_object()) <= 500
    assert len(acc.counts()) == len(acc.points_object())


def test_running_mean_per_voxel() -> None:
    acc = MeshAccumulator(voxel_m=0.01)
    R = Rotation.from_euler("z", 90, degrees=True).as_matrix()
    acc.add(np.array([[1.002, 2.0, 3.0]]), [1.0, 2.0, 3.0], R)
    acc.add(np.array([[1.004, 2.0, 3.0], [1.0, 2.0, 3.5]]), [1.0, 2.0, 3.0], R)
    acc.add(np.empty((0, 3)), [1.0, 2.0, 3.0], R)  # an empty frame still counts
    assert acc.frames == 3
    order = np.argsort(acc.points_object()[:, 2])
    assert np.allclose(acc.points_object()[order], [[0, -0.003, 0], [0, 0, 0.5]])
    assert list(acc.counts()[order]) == [2, 1]


def test_bad_inputs_are_named() -> None:
    acc = MeshAccumulator()
    with pytest.raises(ValueError, match="points_world"):
        acc.add(np.zeros((5, 2)), np.zeros(3), np.eye(3))
    with pytest.raises(ValueError, match="R_world_object"):
        acc.add(np.zeros((5, 3)), np.zeros(3), 2 * np.eye(3))
    with pytest.raises(ValueError, match="centre"):
        acc.add(np.zeros((5, 3)), [0, np.nan, 0], np.eye(3))
    with pytest.raises(ValueError, match="voxel_m"):
        MeshAccumulator(voxel_m=0)
    with pytest.raises(ValueError, match="points_object"):
        build_mesh(np.zeros((10, 3)))  # no volume
    with pytest.raises(ValueError, match="weights"):
        build_mesh(np.random.default_rng(0).normal(size=(10, 3)), weights=np.zeros(10))


def test_encode_decode_round_trip_and_corruption(meshes: dict) -> None:
    v, t = meshes["can"][:2]
    d = encode_mesh(v, t)
    v2, t2 = decode_mesh(d)
    assert np.array_equal(v, v2) and np.array_equal(t, t2)
    assert v2.dtype == np.float32 and t2.dtype == np.int32
    out_of_range = t.astype("<u4")
    out_of_range[0, 0] = len(v)
    nan = v.astype("<f4")
    nan[0, 0] = np.nan
    corrupt = [
        ({**d, "vertex_count": d["vertex_count"] - 1}, "vertices_b64"),
        ({**d, "triangle_count": d["triangle_count"] + 1}, "triangles_b64"),
        ({**d, "triangles_b64": "!!" + d["triangles_b64"][2:]}, "triangles_b64"),
        ({k: x for k, x in d.items() if k != "vertex_count"}, "vertex_count"),
        ({**d, "triangle_count": "7"}, "triangle_count"),
        ({**d, "vertices_b64": None}, "vertices_b64"),
        ({**d, "vertex_count": -1}, "vertex_count"),
        ({**d, "triangles_b64": base64.b64encode(out_of_range.tobytes()).decode()},
         "triangles_b64"),
        ({**d, "vertices_b64": base64.b64encode(nan.tobytes()).decode()}, "vertices_b64"),
    ]
    for bad, field in corrupt:
        with pytest.raises(ValueError, match=field):
            decode_mesh(bad)
    with pytest.raises(ValueError, match="triangles"):
        encode_mesh(v, t + len(v))


def test_obj_loads_in_pybullet(meshes: dict, tmp_path: Path) -> None:
    pybullet = pytest.importorskip("pybullet")
    v, t = meshes["bottle"][:2]
    path = tmp_path / "object.obj"
    write_obj(path, v, t)
    client = pybullet.connect(pybullet.DIRECT)
    try:
        shape = pybullet.createCollisionShape(pybullet.GEOM_MESH, fileName=str(path),
                                              physicsClientId=client)
        visual = pybullet.createVisualShape(pybullet.GEOM_MESH, fileName=str(path),
                                            physicsClientId=client)
        assert shape >= 0 and visual >= 0
        body = pybullet.createMultiBody(1.0, shape, visual, physicsClientId=client)
        lo, hi = pybullet.getAABB(body, physicsClientId=client)
    finally:
        pybullet.disconnect(client)
    # Bullet pads a collision AABB by its contact margin (2 mm here) on every side
    pad = np.r_[v.min(axis=0) - lo, np.asarray(hi) - v.max(axis=0)]
    assert np.all((pad > 0) & (pad < 0.0025)) and np.ptp(pad) < 1e-5

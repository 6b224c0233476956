"""The ray-cast Trisect camera: geometry, occlusion, noise model, dropouts, snow, determinism."""

from __future__ import annotations

import numpy as np
import pytest

from wavegrasp.wavetank.camera import (
    TrisectCamera,
    cylinder_mesh,
    look_at,
    seabed_mesh,
    sphere_mesh,
    transform,
)

CLEAN = {"depth_sigma_at_1m": 0.0, "dropout": 0.0, "dropout_blobs": 0, "snow_per_frame": 0}


def translation(p) -> np.ndarray:
    T = np.eye(4)
    T[:3, 3] = p
    return T


def to_world(cam: TrisectCamera, points: np.ndarray) -> np.ndarray:
    """Points, shape (n, 3), trisect_optical -> world."""
    T = cam.T_world_optical
    return points.astype(float) @ T[:3, :3].T + T[:3, 3]


def looking_down(height: float, **kw) -> tuple[TrisectCamera, list]:
    """A camera `height` m above a 6 m x 6 m seabed, looking straight down."""
    cam = TrisectCamera(look_at([0, 0, height], [0, 0, 0], up=[0, 1, 0]), **kw)
    return cam, [seabed_mesh(6.0, 6.0)]


def sphere_scene(**kw):
    eye, centre, r = np.array([0.0, -1.0, 0.75]), np.array([0.0, 0.0, 0.5]), 0.05
    cam = TrisectCamera(look_at(eye, centre), **kw)
    meshes = [seabed_mesh(4, 4), transform(sphere_mesh(r, resolution=4000), translation(centre))]
    return cam, meshes, eye, centre, r


def test_look_at_is_right_handed_with_z_to_target():
    eye, target = np.array([0.3, -1.0, 0.75]), np.array([0.0, 0.1, 0.5])
    T = look_at(eye, target)
    R = T[:3, :3]
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)
    assert np.linalg.det(R) == pytest.approx(1.0)
    np.testing.assert_allclose(R[:, 2], (target - eye) / np.linalg.norm(target - eye))
    assert abs(R[2, 0]) < 1e-12 and R[2, 1] < 0  # x horizontal, y points down
    np.testing.assert_allclose(T[:3, 3], eye)
    target_optical = R.T @ (target - eye)
    np.testing.assert_allclose(target_optical, [0, 0, np.linalg.norm(target - eye)], atol=1e-12)
    with pytest.raises(ValueError, match="parallel"):
        look_at([0, 0, 1], [0, 0, 0])


def test_meshes_have_the_stated_geometry():
    v = sphere_mesh(0.06).vertex.positions.numpy()
    np.testing.assert_allclose(np.linalg.norm(v, axis=1), 0.06, rtol=1e-6)
    s = sphere_mesh(1.0)
    tri = s.vertex.positions.numpy().astype(float)[s.triangle.indices.numpy()]
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    plane = np.einsum("ij,ij->i", n / np.linalg.norm(n, axis=1, keepdims=True), tri[:, 0])
    assert plane.min() > 0.997  # outward, faceting error < 0.3 % of the radius
    c = cylinder_mesh(0.05, 0.4).vertex.positions.numpy()
    np.testing.assert_allclose(c.min(axis=0), [-0.05, -0.05, -0.2], atol=1e-6)
    np.testing.assert_allclose(c.max(axis=0), [0.05, 0.05, 0.2], atol=1e-6)
    b = transform(seabed_mesh(2, 1), translation([0, 0, 0.1])).vertex.positions.numpy()
    np.testing.assert_allclose(b.min(axis=0), [-1, -0.5, 0.1], atol=1e-6)
    with pytest.raises(ValueError, match="radius"):
        sphere_mesh(-1.0)
    with pytest.raises(ValueError, match="T_world_optical"):
        TrisectCamera(np.eye(3))


def test_sphere_shows_only_its_camera_facing_side():
    cam, meshes, eye, centre, r = sphere_scene(snow_per_frame=0)
    points, labels = cam.capture(meshes, np.random.default_rng(1), return_labels=True)
    on_sphere = to_world(cam, points[labels == 1])
    assert len(on_sphere) > 300
    dist = np.linalg.norm(eye - centre)
    towards_eye = (on_sphere - centre) @ (eye - centre) / dist
    assert towards_eye.min() > -5 * cam.depth_sigma_at_1m * dist**2

    cam, meshes, *_ = sphere_scene(**CLEAN)
    points, labels = cam.capture(meshes, np.random.default_rng(1), return_labels=True)
    on_sphere = to_world(cam, points[labels == 1])
    np.testing.assert_allclose(np.linalg.norm(on_sphere - centre, axis=1), r, atol=1e-4)
    towards_eye = (on_sphere - centre) @ (eye - centre) / dist
    assert towards_eye.min() > r**2 / dist - 1e-4  # inside the tangent cone: visible cap only
    expected_px = np.pi * (cam.focal_px * r / np.sqrt(dist**2 - r**2)) ** 2
    assert len(on_sphere) == pytest.approx(expected_px, rel=0.05)
    # Occlusion: no seabed point lies behind the sphere as seen from the eye.
    bed = to_world(cam, points[labels == 0])
    ray = (bed - eye) / np.linalg.norm(bed - eye, axis=1, keepdims=True)
    miss = np.linalg.norm(np.cross(ray, centre - eye), axis=1)
    assert miss.min() > r - 1e-3


def test_depth_error_grows_with_depth_squared():
    stds = []
    for h in (1.0, 2.0):
        cam, meshes = looking_down(h, dropout=0.0, dropout_blobs=0, snow_per_frame=0)
        points = cam.capture(meshes, np.random.default_rng(2))
        stds.append(np.std(points[:, 2] - h))
        assert stds[-1] == pytest.approx(cam.depth_sigma_at_1m * h**2, rel=0.05)
        # the error moves points along their rays: x / z and y / z stay at the pixel
        assert np.allclose(np.linalg.norm(points[:, :2] / points[:, 2:], axis=1).max(),
                           np.hypot(cam.width / 2 - 0.5, cam.height / 2 - 0.5) / cam.focal_px)
    assert stds[1] / stds[0] == pytest.approx(4.0, rel=0.25)


def test_dropouts_remove_about_the_fraction_set():
    cam, meshes = looking_down(1.0, **CLEAN)
    full = len(cam.capture(meshes, np.random.default_rng(3)))
    assert full == cam.width * cam.height
    cam, meshes = looking_down(1.0, **{**CLEAN, "dropout": 0.2})
    assert len(cam.capture(meshes, np.random.default_rng(3))) / full == pytest.approx(0.8, abs=0.01)
    cam, meshes = looking_down(1.0, **{**CLEAN, "dropout_blobs": 4})
    removed = full - len(cam.capture(meshes, np.random.default_rng(3)))
    assert 0 < removed <= 4 * np.pi * 10.5**2


def test_snow_is_labelled_and_inside_the_frustum_in_front_of_the_scene():
    cam, meshes = looking_down(1.5, snow_per_frame=300)
    points, labels = cam.capture(meshes, np.random.default_rng(4), return_labels=True)
    snow = points[labels == -1].astype(float)
    assert 300 <= len(snow) <= 1200
    x, y, z = snow.T
    assert z.min() >= 0.2 and z.max() <= 1.5 + 0.01  # not behind the seabed
    eps = 1e-6
    assert np.all(np.abs(x) <= z * cam.width / 2 / cam.focal_px + eps)
    assert np.all(np.abs(y) <= z * cam.height / 2 / cam.focal_px + eps)


def test_same_seed_gives_the_same_frame():
    cam, meshes, *_ = sphere_scene()
    tether = transform(cylinder_mesh(0.002, 0.45, 16), translation([0, 0, 0.225]))
    a, la = cam.capture([*meshes, tether], np.random.default_rng(7), return_labels=True)
    b, lb = cam.capture([*meshes, tether], np.random.default_rng(7), return_labels=True)
    c = cam.capture([*meshes, tether], np.random.default_rng(8))
    assert a.dtype == np.float32 and a.shape[1] == 3
    np.testing.assert_array_equal(a, b)
    np.testing.assert_array_equal(la, lb)
    assert a.shape != c.shape or not np.array_equal(a, c)
    assert 20_000 <= len(a) <= 60_000


def test_organized_frame_keeps_every_pixel_nearest_first_and_decodes_as_published():
    cam, meshes, eye, centre, r = sphere_scene(snow_per_frame=300)
    dense = cam.capture(meshes, np.random.default_rng(3))
    image = cam.organize(dense)
    assert image.shape == (cam.height * cam.width, 3) and image.dtype == np.float32
    valid = np.isfinite(image).all(axis=1)
    # Dropouts and holes leave NaN pixels; each pixel holds at most one point, the nearest.
    assert (~valid).sum() > 0 and valid.sum() <= len(dense)
    assert len(dense) - valid.sum() < 0.1 * len(dense)  # only snow shares pixels
    row = image[valid]
    uv = row[:, :2] / row[:, 2:] * cam.focal_px + [cam.width / 2, cam.height / 2]
    u, v = (np.clip(uv.astype(int), 0, [cam.width - 1, cam.height - 1])).T  # snow at an edge
    np.testing.assert_array_equal(v * cam.width + u, np.flatnonzero(valid))
    # Where snow shares a pixel with the surface behind it, the snow (nearer) is kept.
    snow = dense[len(dense) - 300:]
    uv = snow[:, :2] / snow[:, 2:] * cam.focal_px + [cam.width / 2, cam.height / 2]
    u, v = (np.clip(uv.astype(int), 0, [cam.width - 1, cam.height - 1])).T
    at = v * cam.width + u
    assert np.all(image[at, 2] <= snow[:, 2] + 1e-6)

    from wavegrasp.recording_io.ros_msgs import decode_points, encode_organized_points
    from wavegrasp.recording_io.typestore import ros2_typestore

    cdr = encode_organized_points(image, cam.height, cam.width, 1_700_000_000_000_000_000,
                                  "trisect_optical")
    msg = ros2_typestore().deserialize_cdr(cdr, "sensor_msgs/msg/PointCloud2")
    assert (msg.height, msg.width, msg.point_step, msg.is_dense) == (
        cam.height, cam.width, 32, False)
    assert [f.name for f in msg.fields] == ["x", "y", "z", "rgb"]
    cloud = decode_points(cdr)
    np.testing.assert_array_equal(cloud.points, row)
    assert cloud.dropped_nonfinite == (~valid).sum()

"""A Trisect-like stereo camera simulated by ray casting, plus the meshes it looks at.

Frames: `world` is the tank frame (z up, metres, origin on the seabed at the tether anchor);
`trisect_optical` is the camera's optical frame, ROS convention: z forward, x right, y down.
A mesh is an ``open3d.t.geometry.TriangleMesh`` (vertices Float32, triangles Int64) in the frame
named by its producer: the helpers below return meshes in their own body frame; move them into
`world` with :func:`transform` before :meth:`TrisectCamera.capture`.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import open3d as o3d
from scipy.spatial import ConvexHull
from scipy.spatial.transform import Rotation

from wavegrasp.checks import check_fraction, check_positive, check_transform
from wavegrasp.wavetank.body import ObjectSpec

Mesh = o3d.t.geometry.TriangleMesh


def cylinder_mesh(radius: float, length: float, segments: int = 64) -> Mesh:
    """Return a closed cylinder, axis along body z, centred at the origin.

    Parameters
    ----------
    radius, length : float, metres
    segments : int, number of facets around the axis (faceting error r * (1 - cos(pi / segments)))
    """
    for name, value in (("radius", radius), ("length", length)):
        check_positive(name, value)
    return Mesh.create_cylinder(radius=radius, height=length, resolution=segments, split=1)


def sphere_mesh(radius: float, resolution: int = 1500) -> Mesh:
    """Return a sphere centred at the origin: the convex hull of a Fibonacci lattice.

    Parameters
    ----------
    radius : float, metres
    resolution : int, number of vertices; the default (1500 vertices, 2996 triangles) keeps the
        faceting error (largest gap between the facets and the true sphere) at 0.25 % of the
        radius; the error scales like 1 / resolution (4000 vertices: 0.09 %).
    """
    check_positive("radius", radius)
    if resolution < 12:
        raise ValueError(f"resolution must be >= 12 vertices, got {resolution}")
    i = np.arange(resolution) + 0.5
    z = 1.0 - 2.0 * i / resolution
    azimuth = np.pi * (1.0 + 5.0**0.5) * i
    rho = np.sqrt(1.0 - z * z)
    unit = np.column_stack([rho * np.cos(azimuth), rho * np.sin(azimuth), z])
    tri = ConvexHull(unit).simplices
    normals = np.cross(unit[tri[:, 1]] - unit[tri[:, 0]], unit[tri[:, 2]] - unit[tri[:, 0]])
    inward = np.einsum("ij,ij->i", normals, unit[tri[:, 0]]) < 0
    tri[inward] = tri[inward][:, ::-1]  # outward-facing triangles (counter-clockwise)
    return _mesh(radius * unit, tri)


def lathe_mesh(z: np.ndarray, r: np.ndarray, segments: int = 64) -> Mesh:
    """Return the closed solid that the outline ``z``, ``r`` (metres, shape (k,) each, z
    ascending; r > 0) sweeps about body z, as a mesh in body frame, its ends closed flat.

    ``segments`` facets around the axis.
    """
    z, r = np.asarray(z, dtype=float), np.asarray(r, dtype=float)
    if z.shape != r.shape or z.ndim != 1 or len(z) < 2 or np.any(np.diff(z) < 0) or np.any(
            r <= 0):
        raise ValueError("the outline needs k >= 2 heights, ascending, and radii > 0; got "
                         f"z {z.shape}, r {r.shape}")
    phi = np.linspace(0.0, 2 * np.pi, segments, endpoint=False)
    ring = np.column_stack([np.cos(phi), np.sin(phi)])
    rings = [np.column_stack([ri * ring, np.full(segments, zi)])
             for zi, ri in zip(z, r, strict=True)]
    vertices = np.vstack([*rings, [[0.0, 0.0, z[0]], [0.0, 0.0, z[-1]]]])
    j = np.arange(segments)
    k = (j + 1) % segments
    tri = []
    for i in range(len(z) - 1):  # two triangles per facet, outward
        a, b = i * segments, (i + 1) * segments
        tri += [np.column_stack([a + j, a + k, b + k]), np.column_stack([a + j, b + k, b + j])]
    bottom, top, last = len(vertices) - 2, len(vertices) - 1, (len(z) - 1) * segments
    tri += [np.column_stack([np.full(segments, bottom), k, j]),
            np.column_stack([np.full(segments, top), last + j, last + k])]
    return _mesh(vertices, np.vstack(tri))


def object_mesh(spec: ObjectSpec) -> Mesh:
    """The object ``spec`` describes, closed, in its body frame: origin at its volume
    centroid, z along its axis (from the tether's end)."""
    if spec.shape == "sphere":
        return sphere_mesh(spec.radius)
    if spec.shape == "cylinder":
        return cylinder_mesh(spec.radius, spec.length)
    if spec.shape == "box":
        size = np.array([2 * spec.radius, spec.depth, spec.length])
        turn = o3d.core.Tensor(Rotation.from_euler("z", spec.turn_deg, degrees=True)
                               .as_matrix())
        return Mesh.create_box(*size).translate(-size / 2).rotate(turn, o3d.core.Tensor(
            np.zeros(3)))
    if spec.shape == "ellipsoid":
        unit = sphere_mesh(1.0)
        scale = np.array([spec.radius, spec.radius, spec.length / 2], dtype=np.float32)
        return _mesh(unit.vertex.positions.numpy() * scale, unit.triangle.indices.numpy())
    z, r = spec.profile()
    return lathe_mesh(z - spec.attach_offset, r)


def seabed_mesh(size_x: float, size_y: float) -> Mesh:
    """Return a flat rectangle at z = 0, centred at the origin, size_x by size_y m, normal +z."""
    for name, value in (("size_x", size_x), ("size_y", size_y)):
        check_positive(name, value)
    hx, hy = size_x / 2, size_y / 2
    v = np.array([[-hx, -hy, 0.0], [hx, -hy, 0.0], [hx, hy, 0.0], [-hx, hy, 0.0]])
    return _mesh(v, np.array([[0, 1, 2], [0, 2, 3]]))


def _mesh(vertices: np.ndarray, triangles: np.ndarray) -> Mesh:
    mesh = Mesh()
    mesh.vertex.positions = o3d.core.Tensor(np.asarray(vertices, dtype=np.float32))
    mesh.triangle.indices = o3d.core.Tensor(np.asarray(triangles, dtype=np.int64))
    return mesh


def transform(mesh: Mesh, T_world_body: np.ndarray) -> Mesh:
    """Return a copy of `mesh` (vertices in frame body) with vertices in frame world.

    T_world_body : array, shape (4, 4), the body frame's pose in world (maps body -> world).
    """
    return mesh.clone().transform(check_transform("T_world_body", T_world_body))


def look_at(eye: np.ndarray, target: np.ndarray, up: np.ndarray = (0.0, 0.0, 1.0)) -> np.ndarray:
    """Return T_world_optical, shape (4, 4): an optical frame at `eye` looking at `target`.

    eye, target : array, shape (3,), metres, frame world. up : array, shape (3,), frame world,
    the direction that appears up in the image (optical -y); must not be parallel to the view.
    The result has z towards target, x right, y down (right-handed, x = y cross z).
    """
    eye, target, up = (np.asarray(a, dtype=float) for a in (eye, target, up))
    z = target - eye
    if np.linalg.norm(z) < 1e-9:
        raise ValueError("eye and target coincide")
    z /= np.linalg.norm(z)
    x = np.cross(z, up)
    if np.linalg.norm(x) < 1e-9:
        raise ValueError("up is parallel to the viewing direction")
    x /= np.linalg.norm(x)
    T = np.eye(4)
    T[:3, :3] = np.column_stack([x, np.cross(z, x), z])
    T[:3, 3] = eye
    return T


@dataclass
class TrisectCamera:
    """A pinhole stereo depth camera: one ray per pixel, first hit only, Trisect-like defaults.

    Attributes
    ----------
    T_world_optical : array, shape (4, 4), pose of trisect_optical in world.
    width, height : int, pixels; hfov_deg : float, horizontal field of view, degrees (square
        pixels, principal point at the image centre). Defaults 320 x 240 at 70 deg (vertical
        55 deg, focal 228.5 px): with the eye at (0, -1, 0.75) looking at (0, 0, 0.5) over a
        4 m x 4 m seabed and a 6 cm sphere, a frame holds about 37k points.
    max_range_m : float, metres; farthest depth (z in trisect_optical) returned.
    depth_sigma_at_1m : float, metres; 1-sigma depth error at 1 m depth. At depth d the error
        is sigma(d) = depth_sigma_at_1m * d**2, applied along the pixel's ray (the point moves
        along its ray so that its depth changes by N(0, sigma(d)**2)).
    dropout : float, fraction of valid pixels lost at random.
    dropout_blobs : int, per frame, discs of radius 4-10 px, centred anywhere in the image, that
        return nothing (low-texture patches).
    snow_per_frame : int, marine-snow particles per frame, each at a random pixel and a random
        depth between 0.2 m and the scene (or max_range_m on a miss), giving 1-4 points within
        +-1.5 px and 2 mm depth of it; they occlude nothing.
    """

    T_world_optical: np.ndarray
    width: int = 320
    height: int = 240
    hfov_deg: float = 70.0
    max_range_m: float = 3.0
    depth_sigma_at_1m: float = 0.0015
    dropout: float = 0.03
    dropout_blobs: int = 4
    snow_per_frame: int = 150

    def __post_init__(self) -> None:
        self.T_world_optical = check_transform("T_world_optical", self.T_world_optical)
        for name in ("width", "height", "max_range_m"):
            check_positive(name, getattr(self, name))
        if not 0.0 < self.hfov_deg < 180.0:
            raise ValueError(f"hfov_deg must be in (0, 180), got {self.hfov_deg}")
        if self.depth_sigma_at_1m < 0 or self.dropout_blobs < 0 or self.snow_per_frame < 0:
            raise ValueError("depth_sigma_at_1m, dropout_blobs and snow_per_frame must be >= 0")
        check_fraction("dropout", self.dropout)

    @property
    def focal_px(self) -> float:
        """Focal length, pixels (fx = fy)."""
        return self.width / 2 / np.tan(np.radians(self.hfov_deg) / 2)

    @property
    def K(self) -> np.ndarray:
        """Intrinsic matrix, shape (3, 3): pixel (u, v) ~ K @ point in trisect_optical."""
        f = self.focal_px
        return np.array([[f, 0, self.width / 2], [0, f, self.height / 2], [0, 0, 1.0]])

    def pixel_rays(self) -> np.ndarray:
        """Return rays, shape (height * width, 3), trisect_optical, z = 1, row-major, through
        pixel centres (u + 0.5, v + 0.5)."""
        u, v = np.meshgrid(np.arange(self.width) + 0.5, np.arange(self.height) + 0.5)
        return np.column_stack([u.ravel(), v.ravel(), np.ones(u.size)]) @ np.linalg.inv(self.K).T

    def capture(self, meshes: Sequence[Mesh], rng: np.random.Generator,
                return_labels: bool = False) -> np.ndarray | tuple[np.ndarray, np.ndarray]:
        """Return one frame: points, shape (k, 3), float32, metres, frame trisect_optical.

        meshes : meshes with vertices in world; a new RaycastingScene is built from them.
        rng : all randomness (noise, dropouts, snow) comes from it: same state, same frame.
        return_labels : if true, also return labels, shape (k,), int64: the index in `meshes`
            of the mesh each point lies on, -1 for marine snow.
        :meth:`organize` turns the frame into the image a stereo driver publishes.
        """
        scene = o3d.t.geometry.RaycastingScene()
        ids = [scene.add_triangles(m) for m in meshes]
        dirs = self.pixel_rays()  # z = 1, so the hit distance t is the depth
        R, origin = self.T_world_optical[:3, :3], self.T_world_optical[:3, 3]
        rays = np.empty((len(dirs), 6), dtype=np.float32)
        rays[:, :3], rays[:, 3:] = origin, dirs @ R.T
        hit = scene.cast_rays(o3d.core.Tensor(rays))
        depth = hit["t_hit"].numpy().astype(np.float64)
        geometry = hit["geometry_ids"].numpy().astype(np.int64)
        valid = np.isfinite(depth) & (depth <= self.max_range_m)
        valid &= rng.random(len(depth)) >= self.dropout
        valid &= ~self._blob_mask(rng)
        labels = np.searchsorted(ids, geometry[valid])  # geometry id -> index in meshes
        d = depth[valid]
        d = d + rng.normal(size=d.shape) * self.depth_sigma_at_1m * d**2
        points = dirs[valid] * d[:, None]
        snow = self._snow(rng, np.minimum(depth, self.max_range_m))  # misses: t_hit = inf
        points = np.vstack([points, snow]).astype(np.float32)
        if not return_labels:
            return points
        return points, np.concatenate([labels, np.full(len(snow), -1)]).astype(np.int64)

    def organize(self, points: np.ndarray) -> np.ndarray:
        """Return the image, shape (height * width, 3), float32, NaN where empty, that holds
        each of `points` (shape (k, 3), trisect_optical, in front of the camera) at the pixel it
        projects to; where several land on one pixel the nearest wins (as stereo matching
        keeps the front surface)."""
        pts = np.asarray(points, dtype=np.float32)
        image = np.full((self.height * self.width, 3), np.nan, dtype=np.float32)
        if not len(pts):
            return image
        uv = pts[:, :2] / pts[:, 2:3] * self.focal_px + [self.width / 2, self.height / 2]
        u = np.clip(uv[:, 0].astype(int), 0, self.width - 1)
        v = np.clip(uv[:, 1].astype(int), 0, self.height - 1)
        order = np.argsort(pts[:, 2], kind="stable")  # nearest first
        pixel = (v * self.width + u)[order]
        pixel, first = np.unique(pixel, return_index=True)  # each pixel's nearest point
        image[pixel] = pts[order[first]]
        return image

    def _blob_mask(self, rng: np.random.Generator) -> np.ndarray:
        """Return a mask, shape (height * width,), bool: pixels inside this frame's holes."""
        v, u = np.mgrid[0:self.height, 0:self.width] + 0.5
        mask = np.zeros((self.height, self.width), dtype=bool)
        centres = rng.uniform([0, 0], [self.width, self.height], size=(self.dropout_blobs, 2))
        for (cu, cv), r in zip(centres, rng.uniform(4.0, 10.0, self.dropout_blobs), strict=True):
            mask |= (u - cu) ** 2 + (v - cv) ** 2 <= r * r
        return mask.ravel()

    def _snow(self, rng: np.random.Generator, scene_depth: np.ndarray) -> np.ndarray:
        """Return marine-snow points, shape (s, 3), frame trisect_optical, inside the frustum.

        scene_depth : array, shape (height * width,), metres: depth of the first surface per
        pixel (max_range_m where nothing is hit); particles are placed in front of it.
        """
        n, near = self.snow_per_frame, 0.2
        uv = rng.uniform([0, 0], [self.width, self.height], size=(n, 2))
        pix = np.minimum(uv.astype(int), [self.width - 1, self.height - 1])
        far = np.maximum(scene_depth[pix[:, 1] * self.width + pix[:, 0]], near)
        z = rng.uniform(near, far)
        per = rng.integers(1, 5, size=n)
        uv = np.repeat(uv, per, axis=0) + rng.uniform(-1.5, 1.5, size=(per.sum(), 2))
        uv = np.clip(uv, 0.0, [self.width, self.height])
        z = np.clip(np.repeat(z, per) + rng.normal(scale=0.002, size=per.sum()),
                    near, self.max_range_m)
        xy = (uv - [self.width / 2, self.height / 2]) / self.focal_px * z[:, None]
        return np.column_stack([xy, z])

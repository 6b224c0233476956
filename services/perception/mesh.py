"""The object's closed mesh, accumulated over many frames of a one-sided camera view.

:class:`MeshAccumulator`: each frame's points go into the object frame (origin at the fitted
centre, z along the symmetry axis) and a voxel grid of point sums and counts (bounded memory).
:func:`build_mesh` completes the unseen half by rotational symmetry. The count-weighted profile
(rho, z), mirrored to -rho, is projected onto local line fits (moving least squares: removes
the noise band across the surface, keeps the ends); points under half the local peak density go
(outliers, and the blur past an end); the profile's 2-D convex hull is revolved every 5° and
closed by a 3-D convex hull (qhull): watertight and outward by construction, coverage gaps
bridged; the objects are convex, a bottle's small neck aside. Not chosen: Poisson (needs
oriented normals, bulges where data is missing), alpha shapes (radius-sensitive, often
non-manifold), a lathe of the non-convex profile (keeps a neck; hand-written mesher).
Residual bias in the tests' simulation: volume within ±1.5 %; walls ~0.05 mm out; sharp rims
rounded off by ~smooth_m / 2; the 72-gon is 0.13 % small; a sphere's never-seen bottom is cut
flat (~0.5 %). A *biased* (not noisy) fitter centre or axis moves the mesh one-to-one.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from scipy.sparse import csr_matrix
from scipy.spatial import ConvexHull, QhullError, cKDTree

_OFFSET = 1 << 20  # voxel index offset, so keys are non-negative (±3 km at 3 mm)


def check_points(name: str, points: np.ndarray) -> np.ndarray:
    """Return `points` as an array, shape (n, 3), float64; ValueError unless finite."""
    points = np.asarray(points, dtype=float)
    if points.ndim != 2 or points.shape[1] != 3 or not np.all(np.isfinite(points)):
        raise ValueError(f"{name} must be finite with shape (n, 3), got shape {points.shape}")
    return points


def check_rotation(name: str, R: np.ndarray) -> np.ndarray:
    """Return `R` as an array, shape (3, 3), float64; ValueError unless a proper rotation."""
    R = np.asarray(R, dtype=float)
    if R.shape != (3, 3) or not (np.allclose(R @ R.T, np.eye(3), atol=1e-5)
                                 and np.linalg.det(R) > 0):
        raise ValueError(f"{name} must be a proper rotation matrix, shape (3, 3)")
    return R


class MeshAccumulator:
    """Running per-voxel mean of the object's points, in the object frame.

    Parameters
    ----------
    voxel_m : float, metres
        Voxel edge.
    max_points : int
        Most voxels kept: beyond it the voxels with the fewest points go, down to 90 %.
    """

    def __init__(self, voxel_m: float = 0.003, max_points: int = 20000) -> None:
        if not (np.isfinite(voxel_m) and voxel_m > 0):
            raise ValueError(f"voxel_m must be a finite number > 0, got {voxel_m!r}")
        if max_points < 1:
            raise ValueError(f"max_points must be >= 1, got {max_points!r}")
        self.voxel_m, self.max_points, self.frames = float(voxel_m), int(max_points), 0
        self._keys, self._sums = np.empty(0, np.int64), np.empty((0, 4))  # sorted; x y z n

    def add(self, points_world: np.ndarray, centre: np.ndarray, R_world_object: np.ndarray) -> None:
        """Merge one frame.

        Parameters
        ----------
        points_world : array, shape (n, 3), metres, frame world
            The object's points.
        centre : array, shape (3,), metres, frame world
            The fitted centre: the object frame's origin.
        R_world_object : array, shape (3, 3)
            Rotation from object to world; its z column is the symmetry axis.
        """
        points_world = check_points("points_world", points_world)
        centre = check_points("centre", np.reshape(centre, (1, -1)))[0]
        p = (points_world - centre) @ check_rotation("R_world_object", R_world_object)
        ijk = np.floor(p / self.voxel_m).astype(np.int64) + _OFFSET
        if len(p) and (ijk.min() < 0 or ijk.max() >= 2 * _OFFSET):
            raise ValueError("points_world lie implausibly far (> 1e6 voxels) from centre")
        self.frames += 1
        keys, inv = np.unique((ijk[:, 0] << 42) | (ijk[:, 1] << 21) | ijk[:, 2],
                              return_inverse=True)
        sums = np.stack([np.bincount(inv, c, len(keys)) for c in np.c_[p, np.ones(len(p))].T], 1)
        at = np.searchsorted(self._keys, keys)
        known = at < len(self._keys)
        known[known] = self._keys[at[known]] == keys[known]
        self._sums[at[known]] += sums[known]
        self._keys = np.insert(self._keys, at[~known], keys[~known])
        self._sums = np.insert(self._sums, at[~known], sums[~known], axis=0)
        if len(self._keys) > self.max_points:  # keep the best-supported voxels, in key order
            keep = np.sort(np.argsort(-self._sums[:, 3])[: int(0.9 * self.max_points)])
            self._keys, self._sums = self._keys[keep], self._sums[keep]

    def points_object(self) -> np.ndarray:
        """Voxel means, array, shape (m, 3), metres, frame object."""
        return self._sums[:, :3] / self._sums[:, 3:]

    def counts(self) -> np.ndarray:
        """Points merged into each voxel, array, shape (m,), int64 (weights for build_mesh)."""
        return self._sums[:, 3].astype(np.int64)


def _pairs(a: np.ndarray, b: np.ndarray, radius: float) -> tuple[np.ndarray, ...]:
    """Index pairs (i into a, j into b) closer than `radius`, and Wendland kernel weights."""
    pairs = cKDTree(a).sparse_distance_matrix(cKDTree(b), radius, output_type="ndarray")
    return pairs["i"], pairs["j"], (1.0 - (pairs["v"] / radius) ** 2) ** 2


def _mls_project(points: np.ndarray, weights: np.ndarray, radius: float) -> np.ndarray:
    """Points, shape (n, d), projected onto the weighted line (d = 2) / plane (d = 3) fit of
    their neighbours within `radius`; iterated, each fit centred on the last projection."""
    q, (n, d) = points.copy(), points.shape
    outer = (points[:, :, None] * points[:, None, :]).reshape(n, d * d)
    for _ in range(6):
        i, j, k = _pairs(q, points, radius)
        A = csr_matrix((weights[j] * k, (i, j)), shape=(n, n))  # row-normalised below
        wsum = np.asarray(A.sum(axis=1)).ravel()
        ok = wsum > 0
        mean, second = (np.asarray(A @ x)[ok] / wsum[ok, None] for x in (points, outer))
        cov = second.reshape(-1, d, d) - mean[:, :, None] * mean[:, None, :]
        normal = np.linalg.eigh(cov)[1][:, :, 0]  # smallest-eigenvalue direction
        q[ok] -= np.sum((q[ok] - mean) * normal, axis=1)[:, None] * normal
    return q


def _dense(points: np.ndarray, weights: np.ndarray, radius: float, profile: bool) -> np.ndarray:
    """Mask: kernel density >= half the highest within 2 `radius` (a blurred end has half the
    density where the sharp end lies); for a (rho, z) `profile`, per unit surface (/ rho)."""
    i, j, k = _pairs(points, points, radius)
    if profile:
        k = k / np.maximum(np.abs(points[j, 0]), radius)
    density = np.bincount(i, k * weights[j], len(points))
    i, j, _ = _pairs(points, points, 2 * radius)
    peak = density.copy()
    np.maximum.at(peak, i, density[j])
    return density >= 0.5 * peak


def build_mesh(points_object: np.ndarray, symmetric: bool = True,
               weights: np.ndarray | None = None, smooth_m: float = 0.006
               ) -> tuple[np.ndarray, np.ndarray]:
    """Closed, watertight, outward-oriented convex mesh of the accumulated points.

    Parameters
    ----------
    points_object : array, shape (m, 3), metres, frame object
        Accumulated points (e.g. :meth:`MeshAccumulator.points_object`).
    symmetric : bool
        Complete the unseen side by rotational symmetry about the object's z axis. If False,
        the hull of the (smoothed) points alone: closed, but too small for a one-sided view.
    weights : array, shape (m,), optional
        Points behind each input point (:meth:`MeshAccumulator.counts`; default ones). Needed
        for an unbiased result: a voxel in the noise tail holds few points.
    smooth_m : float, metres
        Neighbourhood radius of the line/plane fits and the density test; 0: none.

    Returns
    -------
    vertices : array, shape (v, 3), float32, metres, frame object
    triangles : array, shape (t, 3), int32, counter-clockwise seen from outside
    """
    p = check_points("points_object", points_object)
    w = np.ones(len(p)) if weights is None else np.asarray(weights, dtype=float)
    if w.shape != (len(p),) or not np.all(np.isfinite(w) & (w > 0)):
        raise ValueError(f"weights must have shape ({len(p)},) and be finite > 0")
    try:
        if symmetric:
            rho = np.hypot(p[:, 0], p[:, 1])
            prof = np.concatenate([np.c_[rho, p[:, 2]], np.c_[-rho, p[:, 2]]])
            _, inv = np.unique(np.floor(prof / max(smooth_m / 6, 1e-4)).astype(np.int64),
                               axis=0, return_inverse=True)
            pw = np.bincount(inv.ravel(), np.r_[w, w])
            prof = np.stack([np.bincount(inv.ravel(), np.r_[w, w] * x) / pw for x in prof.T], 1)
            if smooth_m > 0:
                prof = _mls_project(prof, pw, smooth_m)[_dense(prof, pw, smooth_m, True)]
            outline = prof[ConvexHull(prof).vertices]  # counter-clockwise
            arc = np.cumsum(np.linalg.norm(outline - np.roll(outline, 1, axis=0), axis=1))
            step = max(smooth_m, 1e-3) / 2  # thin a smooth outline: fewer facets, same area
            outline = outline[np.r_[True, np.diff(np.floor(arc / step)) > 0]]
            rim = outline[outline[:, 0] >= 0]
            ang = np.radians(np.arange(0, 360, 5))  # 72 copies of the profile
            pts = np.stack([np.outer(rim[:, 0], np.cos(ang)), np.outer(rim[:, 0], np.sin(ang)),
                            np.repeat(rim[:, 1:], len(ang), axis=1)], axis=-1).reshape(-1, 3)
        else:
            pts = _mls_project(p, w, smooth_m)[_dense(p, w, smooth_m, False)] if smooth_m else p
        hull = ConvexHull(pts)
    except (QhullError, ValueError, IndexError) as e:
        raise ValueError(f"points_object do not span a volume ({len(p)} points): {e}") from e
    tri, v = hull.simplices.copy(), hull.points
    cross = np.cross(v[tri[:, 1]] - v[tri[:, 0]], v[tri[:, 2]] - v[tri[:, 0]])
    flip = np.sum(cross * hull.equations[:, :3], axis=1) < 0  # equations: outward normals
    tri[flip] = tri[flip][:, ::-1]
    used, tri = np.unique(tri, return_inverse=True)
    return v[used].astype(np.float32), tri.reshape(-1, 3).astype(np.int32)


def mesh_volume(vertices: np.ndarray, triangles: np.ndarray) -> float:
    """Enclosed volume, m³, of a closed mesh (signed tetrahedra; positive if outward)."""
    v = np.asarray(vertices, dtype=float)[np.asarray(triangles)]
    return float(np.sum(v[:, 0] * np.cross(v[:, 1], v[:, 2])) / 6.0)


def write_obj(path: str | Path, vertices: np.ndarray, triangles: np.ndarray) -> None:
    """Write a Wavefront OBJ (``v``, 1-based ``f``; metres) that PyBullet's
    ``createCollisionShape`` / ``createVisualShape(fileName=...)`` load."""
    v, t = check_points("vertices", vertices), np.asarray(triangles, dtype=np.int64) + 1
    with Path(path).open("w") as f:
        np.savetxt(f, v, "v %.6f %.6f %.6f", header="wavegrasp object mesh, metres, frame object")
        np.savetxt(f, t, "f %d %d %d")

"""Which of a camera frame's points cross the tether: all of the object's region, and as
many of the rest as the budget leaves, picked at random (an even thinning, whatever order
the camera sends its points in).

Perception tracks the object in a few hundred points around where it was; the rest of the
scene serves to find it (clusters of surfaces, judged at the cloud's own point spacing) and
the seabed (fitted on a 2 cm voxel grid), both of which hold at a fraction of the points.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from wavegrasp.perception.fit import check_points

#: A PointCloud2 of x, y, z float32: bytes a point, and about what its header takes.
POINT_BYTES = 12
HEADER_BYTES = 200
#: The object's region never takes more than this share of a frame's budget: the scene
#: around it still crosses (a near object at a camera's full resolution).
REGION_SHARE = 0.8


@dataclass(frozen=True)
class Region:
    """A ball around the object: centre : array, shape (3,), metres, the cloud's frame;
    radius_m : metres."""

    centre: np.ndarray
    radius_m: float

    def __post_init__(self) -> None:
        if np.shape(self.centre) != (3,) or not np.isfinite(self.centre).all():
            raise ValueError(f"region centre must be 3 finite numbers, got {self.centre!r}")
        if not self.radius_m > 0:
            raise ValueError(f"region radius must be > 0 m, got {self.radius_m}")


def frame_budget(mbit_s: float, period_s: float) -> int:
    """Points a frame may carry to stay within ``mbit_s`` Mbit/s at one frame every
    ``period_s`` seconds (at least one)."""
    if not mbit_s > 0 or not period_s > 0:
        raise ValueError(f"budget {mbit_s} Mbit/s and frame period {period_s} s must be > 0")
    return max(1, int((mbit_s * 1e6 / 8 * period_s - HEADER_BYTES) // POINT_BYTES))


def keep_mask(points: np.ndarray, region: Region | None, budget: int,
              rng: np.random.Generator) -> np.ndarray:
    """Which points to send: a bool array, shape (n,).

    points : array, shape (n, 3), metres, the camera's frame; region : the object's, or
    None (not followed: the whole frame is thinned alike); budget : points at most (in
    expectation: each point is kept with its share's probability).
    """
    pts = check_points(points, min_points=0)
    n = len(pts)
    if n <= budget:
        return np.ones(n, dtype=bool)
    inside = np.zeros(n, dtype=bool)
    if region is not None:
        d = pts - region.centre.astype(pts.dtype)
        inside = np.einsum("ij,ij->i", d, d) <= region.radius_m ** 2
    n_in = int(inside.sum())
    p_in = min(1.0, REGION_SHARE * budget / n_in) if n_in else 0.0
    n_out = n - n_in
    p_out = min(1.0, max(0.0, budget - p_in * n_in) / n_out) if n_out else 0.0
    return rng.random(n) < np.where(inside, p_in, p_out)

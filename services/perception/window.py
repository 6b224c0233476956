"""Where in an organized cloud the object can be, so that only those pixels are read.

An organized cloud (a stereo camera's: height x width, a point per pixel, NaN where matching
found nothing) holds each point at the pixel its ray goes through: in a rectified camera a
point's x / z is linear in its column and y / z in its row. :meth:`PixelRays.learn` finds
those lines from one frame; :meth:`PixelRays.window` gives the rows and columns of every
pixel whose ray meets a sphere, the region perception searches while it follows the object.
Every point inside the sphere is inside the window, in the order the whole cloud has it, so
following reads the window and finds what it would have found in the whole cloud: a 672 x
376 frame is 252 672 points, the window round a 15 cm object a metre away a few thousand.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass

import numpy as np

from wavegrasp.recording_io.ros_msgs import Cloud, CloudView

log = logging.getLogger("wavegrasp.perception")

#: A cloud whose points lie further than this from the lines, pixels, is not organized by
#: its rays (it is not read in windows).
MAX_RESIDUAL_PX = 2.0
#: Points needed to learn the lines from.
MIN_POINTS = 100
#: Frames read whole to learn an organized cloud's pixel rays from before giving up.
RAY_TRIES = 10


@dataclass(frozen=True)
class PixelRays:
    """column = fx * x / z + cx and row = fy * y / z + cy, give or take ``margin_px``, for
    every point of a ``height`` x ``width`` organized cloud (camera frame, z ahead)."""

    fx: float
    cx: float
    fy: float
    cy: float
    margin_px: float
    width: int
    height: int

    @classmethod
    def learn(cls, xyz: np.ndarray) -> PixelRays | None:
        """The lines of an organized cloud's ``xyz`` (height, width, 3), metres, camera frame;
        None if it has too few points ahead of the camera or they do not lie on lines."""
        height, width = xyz.shape[:2]
        z = xyz[..., 2]
        rows, cols = np.nonzero(np.isfinite(xyz).all(axis=-1) & (z > 0))
        if len(rows) < MIN_POINTS or width < 2 or height < 2:
            return None
        p = np.asarray(xyz[rows, cols], dtype=float)
        fit = []
        for slope, index in ((p[:, 0] / p[:, 2], cols), (p[:, 1] / p[:, 2], rows)):
            if np.ptp(slope) <= 0:
                return None
            f, c = np.polyfit(slope, index + 0.5, 1)
            fit.append((f, c, float(np.abs(index + 0.5 - (f * slope + c)).max())))
        (fx, cx, ex), (fy, cy, ey) = fit
        if max(ex, ey) > MAX_RESIDUAL_PX:
            return None
        return cls(fx, cx, fy, cy, max(ex, ey) + 1.0, width, height)

    def window(self, centre: np.ndarray, radius: float) -> tuple[slice, slice] | None:
        """The rows and columns holding every point within ``radius`` metres of ``centre``
        (3,), metres, camera frame; None where the sphere reaches the camera's plane (read
        everything)."""
        x, y, z = (float(v) for v in centre)
        if z <= radius:
            return None
        return (_span(y, z, radius, self.fy, self.cy, self.margin_px, self.height),
                _span(x, z, radius, self.fx, self.cx, self.margin_px, self.width))


def _span(a: float, z: float, r: float, f: float, c: float, margin: float, size: int
          ) -> slice:
    """The pixels along one image axis whose slopes a / z reach the circle of radius ``r``
    round (a, z): between the slopes of its two tangents through the camera."""
    root = r * math.sqrt(a * a + z * z - r * r)
    ends = [f * (a * z + s * root) / (z * z - r * r) + c for s in (-1.0, 1.0)]
    lo = max(0, math.floor(min(ends) - margin))
    hi = min(size, math.ceil(max(ends) + margin) + 1)
    return slice(lo, max(lo, hi))


def thinned(window: tuple[slice, slice], max_pixels: int) -> tuple[slice, slice]:
    """``window`` (rows, columns, step 1) at the smallest stride s, every s-th row and
    column, that leaves at most ``max_pixels`` pixels: a full-resolution stereo camera sees
    a near object in more points than a centroid needs (``python -m
    wavegrasp.perception.evaluate`` at 672 x 376: the window 11 189 points, 8.4 ms a frame;
    every second row and column 2 791 points, 5.2 ms, centroid RMSE 0.52 mm against 0.30)."""
    if max_pixels < 1:
        raise ValueError(f"max_pixels must be at least 1, got {max_pixels}")
    rows, cols = window
    pixels = (rows.stop - rows.start) * (cols.stop - cols.start)
    stride = max(1, math.ceil(math.sqrt(pixels / max_pixels)))
    while math.ceil((rows.stop - rows.start) / stride) * math.ceil(
            (cols.stop - cols.start) / stride) > max_pixels:
        stride += 1
    return slice(rows.start, rows.stop, stride), slice(cols.start, cols.stop, stride)


class WindowReader:
    """Reads camera frames as perception needs them: a dense cloud whole; an organized one,
    once its pixel rays are learnt (from a whole frame) and while the object is followed,
    only the window of pixels that can hold the points perception will search, thinned to
    about ``max_points`` (:func:`thinned`, judged by the share of the last window's pixels
    that held a point); otherwise, or where the window holds none, whole.
    ``read_windows`` False: every frame whole."""

    def __init__(self, read_windows: bool = True, max_points: int = 10_000) -> None:
        if max_points < 1:
            raise ValueError(f"max_points must be at least 1, got {max_points}")
        self.read_windows, self.max_points = read_windows, max_points
        self.rays: PixelRays | None = None
        self.tries = 0
        self.fill = 1.0  # of the pixels of the last window read, the share holding a point

    def read(self, view: CloudView, region: tuple[np.ndarray, float] | None,
             T_world_cam: np.ndarray | None) -> tuple[Cloud, bool]:
        """The frame's finite points, and whether they were read in a window. ``region``:
        where perception will search (centre (3,), metres, world; radius, metres) or None;
        ``T_world_cam`` (4, 4): the camera's pose, or None if not known yet."""
        window = self.window(view, region, T_world_cam) if view.organized else None
        if window is not None:
            rows, cols = thinned(window, int(self.max_points / self.fill))
            cloud = view.points(rows, cols)
            pixels = len(range(rows.start, rows.stop, rows.step)) * len(
                range(cols.start, cols.stop, cols.step))
            self.fill = max(len(cloud.points) / max(pixels, 1), 1e-3)
            if len(cloud.points):
                return cloud, True
        cloud = view.points()
        if view.organized and self.rays is None and self.tries < RAY_TRIES:
            self.tries += 1
            self.rays = PixelRays.learn(view.xyz)
            if self.rays is None and self.tries == RAY_TRIES:
                log.warning("the organized cloud's points do not lie on their pixels' rays: "
                            "every frame is read whole")
        return cloud, False

    def window(self, view: CloudView, region: tuple[np.ndarray, float] | None,
               T_world_cam: np.ndarray | None) -> tuple[slice, slice] | None:
        """The rows and columns of ``view`` to read (step 1), or None: read it all."""
        rays = self.rays if self.read_windows else None
        if rays is None or region is None or T_world_cam is None or (
                view.xyz.shape[:2] != (rays.height, rays.width)):
            return None
        predicted, radius = region
        return rays.window((predicted - T_world_cam[:3, 3]) @ T_world_cam[:3, :3], radius)

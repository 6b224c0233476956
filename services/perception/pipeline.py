"""Per-frame perception: from a raw camera cloud to the tracked object's volume centroid.

Acquisition (no track yet): everything in the workspace, seabed plane removed (RANSAC), marine
snow and the thin tether removed by surface density, clustered, and the most object-like
cluster taken. Tracking: only points near where the track predicts the object are looked at,
which keeps the hot path to a few hundred points; the cluster nearest the prediction is the
object (continuity, not the biggest blob). The centroid comes from fitting the object's shape
(sphere, cylinder, box or another solid of revolution: fit.py, box.py, revolution.py), learnt
over the first frames and then held fixed, so the camera's one-sided view does not pull it
towards the camera.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass, field, replace

import numpy as np
import open3d as o3d
from pydantic import BaseModel, Field
from scipy.spatial import cKDTree

from wavegrasp.perception.fit import (
    LINE_WIDTH_M,
    ShapeFit,
    check_points,
    line_width,
    segment_plane,
)
from wavegrasp.perception.shape import fit_shape


class PerceptionConfig(BaseModel):
    """Tuning of the pipeline. Lengths metres in ``world``."""

    workspace_min: tuple[float, float, float] = (-1.5, -1.5, -0.5)
    workspace_max: tuple[float, float, float] = (1.5, 1.5, 2.0)
    seabed_distance_m: float = Field(0.02, description="points this close to the seabed go")
    density_radius_spacings: float = Field(3.5, description="neighbourhood, in point spacings")
    min_neighbours: int = Field(14, description="fewer: snow or tether, not a surface")
    cluster_eps_spacings: float = 2.5
    join_m: float = Field(0.05, description="clusters this close to the object's are part of "
                          "it: a bottle's shoulder facing away from the camera leaves its "
                          "neck apart")
    join_min_width_m: float = Field(LINE_WIDTH_M, description="unless they are lines: their "
                                    "spread across their length (standard deviation) is less "
                                    "(the tether's 1.6 mm, a 4.8 cm neck's 7-8 mm)")
    object_size_m: tuple[float, float] = (0.03, 0.40)
    min_object_points: int = 30
    gate_m: float = Field(0.10, description="search radius beyond the object's own size")
    lost_after_frames: int = 5
    learn_frames: int = 15
    max_sigma_m: float = Field(0.005, description="a less certain centroid is not reported")
    max_rms_ratio: float = Field(3.0, description="once the shape is learnt, a fit this many "
                                 "times farther off the points than the learnt fits were "
                                 "typically is a failed fit (a wrong axis), not reported")
    seabed_refit_frames: int = 100
    span_frames: int = Field(50, description="frames whose ends along the axis are pooled: "
                             "a bottle's neck is seen in some views, not all")
    speed_memory_s: float = Field(3.0, description="the object's top speed over this long "
                                  "(a sway's period or more) widens the search once it has "
                                  "gone unseen longer than a frame")


@dataclass
class FrameResult:
    """One frame's outcome: the fit (None if no object), the object's points in world and,
    for a shape with an axis, where along it the object ends (:func:`axial_span`)."""

    fit: ShapeFit | None
    points: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    reason: str | None = None
    span: tuple[float, float] | None = None


def to_world(points: np.ndarray, T: np.ndarray) -> np.ndarray:
    """points : array, shape (n, 3), frame A; T : T_world_A (4, 4) -> shape (n, 3), world."""
    return points @ T[:3, :3].T + T[:3, 3]


def fit_seabed(points: np.ndarray, viewpoint: np.ndarray) -> np.ndarray | None:
    """Plane (a, b, c, d), unit normal towards the camera, of the largest plane; None if weak."""
    if len(points) < 500:
        return None
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points.astype(np.float64)))
    pcd = pcd.voxel_down_sample(0.02)
    if len(pcd.points) < 100:
        return None
    plane, inliers = segment_plane(np.asarray(pcd.points), 0.01)
    if len(inliers) < 0.3 * len(pcd.points):
        return None
    plane = plane / np.linalg.norm(plane[:3])
    return -plane if plane[:3] @ viewpoint + plane[3] < 0 else plane


def surface_points(points: np.ndarray, cfg: PerceptionConfig) -> tuple[np.ndarray, float]:
    """Keep points on surfaces (dense neighbourhoods): drops snow specks and the thin tether.

    Returns the kept points and the point spacing (median nearest-neighbour distance).
    """
    if len(points) < cfg.min_object_points:
        return points[:0], 0.0
    tree = cKDTree(points)
    spacing = float(np.median(tree.query(points, k=2)[0][:, 1]))
    counts = tree.query_ball_point(points, cfg.density_radius_spacings * spacing,
                                   return_length=True)
    return points[counts >= cfg.min_neighbours], spacing


def clusters(points: np.ndarray, eps: float, min_size: int = 4) -> list[np.ndarray]:
    """Euclidean clusters (open3d DBSCAN) of at least ``min_size`` points, largest first."""
    if len(points) < min_size:
        return []
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points.astype(np.float64)))
    labels = np.asarray(pcd.cluster_dbscan(eps, 4))
    found = [points[labels == k] for k in range(labels.max() + 1)]
    return sorted((c for c in found if len(c) >= min_size), key=len, reverse=True)


def joined(part: np.ndarray, parts: list[np.ndarray], gap_m: float, min_width_m: float
           ) -> np.ndarray:
    """``part`` and every other of ``parts`` with a point within ``gap_m`` metres of it and
    spread at least ``min_width_m`` across its length (standard deviation, metres).

    part : array, shape (n, 3); parts : arrays, shape (m_i, 3), ``part`` among them.
    A bottle hanging neck down, seen from above, hides its shoulder: its neck is a cluster of
    its own 3 cm below its body, and the body alone put the volume centroid 15 mm high
    (random-59-031). What is left of the tether near the object is a line: joined, it
    stretched a bottle's outline from 17.6 to 21-26 cm (random-61-017)."""
    tree = cKDTree(part)
    near = [q for q in parts if q is not part and tree.query(q)[0].min() <= gap_m
            and line_width(q) >= min_width_m]
    return np.vstack([part, *near]) if near else part


class Perception:
    """Tracks one object through a stream of clouds. Drive it with :meth:`process`."""

    def __init__(self, cfg: PerceptionConfig | None = None) -> None:
        self.cfg = cfg or PerceptionConfig()
        self.seabed: np.ndarray | None = None
        self.track: np.ndarray | None = None  # last centroid, world
        self.fits: deque[tuple[float, np.ndarray]] = deque(maxlen=3)  # (s, centre) of the track
        self.last_stamp_ns = 0
        self.misses = 0
        self.frame_ns: int | None = None  # the last frame's stamp, the object seen or not
        self.intervals: deque[float] = deque(maxlen=20)  # s, between the last frames
        self.prior: ShapeFit | None = None
        self.axis: np.ndarray | None = None  # the last reported fit's axis, world
        self.frame: np.ndarray | None = None  # and a box's axes (columns)
        self.learnt: list[ShapeFit] = []
        self.disagreed = 0  # fits in a row that differed from the learnt ones
        self.frames = 0
        self.spans: deque[tuple[float, float]] = deque(maxlen=self.cfg.span_frames)
        self.span_axis: np.ndarray | None = None  # the direction self.spans are along
        self.speeds: deque[tuple[int, float]] = deque()  # (stamp ns, m/s) between fits

    def process(self, points: np.ndarray, T_world_cam: np.ndarray, stamp_ns: int) -> FrameResult:
        """points : array, shape (n, 3), metres, camera frame; T_world_cam : (4, 4)."""
        self.frames += 1
        self.intervals = self._intervals_with(stamp_ns)
        self.frame_ns = stamp_ns
        eye = T_world_cam[:3, 3]
        if self.track is None:
            found = self._acquire(points, T_world_cam, eye)
        else:
            found = self._follow(points, T_world_cam, stamp_ns)
        if isinstance(found, str):
            return self._miss(found)
        candidate, near = found
        try:
            check_points(candidate, self.cfg.min_object_points)
            fit = fit_shape(candidate, eye, self._start(), raw=near)
        except ValueError as exc:
            return self._miss(f"shape fit failed: {exc}")
        if self.prior is not None and self.prior.far_off(fit.rms, self.cfg.max_rms_ratio):
            # Its sigma says nothing of it: measured 17 frames of a tilting cylinder 57 mm off
            # with sigma 1 mm, its axis 90 degrees out, 6 mm off the points against 0.5.
            return self._miss(f"fit failed: {fit.rms * 1e3:.1f} mm off the points, the learnt "
                              f"shape {self.prior.rms * 1e3:.1f} mm")
        if fit.sigma > self.cfg.max_sigma_m:
            return self._miss(f"partial view: centroid uncertain by {fit.sigma * 1e3:.0f} mm")
        if self.prior is None and not consistent_with(fit, self.learnt):
            # The first fits are taken as they come: where none since has agreed with them
            # for as many frames as a shape is learnt from, they were the odd ones out, and
            # learning starts again (a thin box's first three, a sphere of 90 m among them,
            # refused the next 90 frames: random-151-020).
            self.disagreed += 1
            if self.disagreed >= self.cfg.learn_frames:
                self.learnt, self.disagreed = [], 0
            return self._miss("partial view: the shape differs from the frames before")
        self.disagreed = 0
        self._update_track(fit, stamp_ns)
        return FrameResult(fit, candidate[fit.inliers], span=self._span(candidate, fit))

    def _span(self, points: np.ndarray, fit: ShapeFit) -> tuple[float, float] | None:
        """The object's ends along ``fit``'s axis (:func:`axial_span`), pooled over the last
        ``span_frames`` frames (the 10th and 90th percentiles of their lower and upper
        ends: what most views miss, some see), each oriented along the first fit's axis
        (a lying object's axis flips between frames)."""
        span = axial_span(points, fit)
        if span is None:
            return None
        if self.span_axis is None:
            self.span_axis = fit.axis
        flip = fit.axis @ self.span_axis < 0
        self.spans.append((-span[1], -span[0]) if flip else span)
        lows, highs = np.array(self.spans).T
        lo, hi = float(np.percentile(lows, 10)), float(np.percentile(highs, 90))
        return (-hi, -lo) if flip else (lo, hi)

    def _start(self) -> ShapeFit | None:
        """The learnt shape, its axis (a box: its axes) where the last fit found it: a
        tethered cylinder tilts 40 degrees as it swings, and started from the axis learnt at
        the first frames its fit slid to a wrong axis (measured: 17 frames 57 mm off, every
        few seconds); a box turns as it sways, and its faces matched to the axes learnt at
        the first frames were taken for other sides (a 4 x 6 x 29 cm box's centre put 12 cm
        off in one frame in five)."""
        if self.prior is None or self.axis is None:
            return self.prior
        if self.prior.shape == "box" and self.frame is not None:
            return replace(self.prior, frame=self.frame)
        if self.prior.shape not in ("cylinder", "revolution"):
            return self.prior
        return replace(self.prior, axis=self.axis)

    def _miss(self, reason: str) -> FrameResult:
        self.misses += 1
        if self.misses >= self.cfg.lost_after_frames:
            self.track = None
        return FrameResult(None, reason=reason)

    def _acquire(self, points: np.ndarray, T: np.ndarray, eye: np.ndarray
                 ) -> tuple[np.ndarray, np.ndarray] | str:
        """The most object-like cluster in the workspace and the points it was found among
        (before the density filter), world; or why none."""
        cfg = self.cfg
        world = to_world(points, T)
        inside = np.all((world >= cfg.workspace_min) & (world <= cfg.workspace_max), axis=1)
        world = world[inside]
        if self.seabed is None or self.frames % cfg.seabed_refit_frames == 0:
            self.seabed = fit_seabed(world, eye) if len(world) else None
        world = self._above_seabed(world)
        dense, spacing = surface_points(world, cfg)
        lo, hi = cfg.object_size_m
        found = clusters(dense, cfg.cluster_eps_spacings * max(spacing, 1e-3))
        for c in found:
            if len(c) >= cfg.min_object_points and lo <= np.linalg.norm(np.ptp(c, axis=0)) \
                    <= hi * 1.5:
                return joined(c, found, cfg.join_m, cfg.join_min_width_m), world
        return "no object-like cluster in the workspace"

    def _intervals_with(self, stamp_ns: int) -> deque[float]:
        """The intervals between the last frames once a frame stamped ``stamp_ns`` came."""
        intervals = deque(self.intervals, maxlen=self.intervals.maxlen)
        if self.frame_ns is not None and stamp_ns > self.frame_ns:
            intervals.append((stamp_ns - self.frame_ns) * 1e-9)
        return intervals

    def search_region(self, stamp_ns: int) -> tuple[np.ndarray, float] | None:
        """Where :meth:`process` will look for the object in the next frame, stamped
        ``stamp_ns``: the centre (3,), metres, world, and radius, metres, of the sphere whose
        points it takes; None while it has no track (it searches the whole workspace)."""
        if self.track is None:
            return None
        return self._region(stamp_ns, self._intervals_with(stamp_ns))

    def _region(self, stamp_ns: int, intervals: deque[float]) -> tuple[np.ndarray, float]:
        cfg = self.cfg
        dt = max(0.0, (stamp_ns - self.last_stamp_ns) * 1e-9)
        predicted = self._predicted(stamp_ns, intervals)
        # Its largest extent: a flat ellipsoid's length (along its axis) is less than its
        # width, and searched for within that, a 5 Hz camera lost it in one frame in three.
        size = max(self.prior.length, 2.0 * self.prior.radius) if self.prior is not None \
            else cfg.object_size_m[1] / 2
        # Where it may be grows with the time it has gone unseen beyond a frame, at its top
        # speed of late: a swaying object turns back, and a 5 Hz camera's frames a few
        # misses apart found it 10-25 cm off the track's straight line (random-67-000, lost
        # for a second after each miss, 16 % of frames observed). Not on every frame: the
        # wider search took in more than the object, and a 30 Hz camera's ellipsoid was
        # refused in 172 frames of 900, not 52 (random-7-028).
        unseen = dt - float(np.median(intervals)) if intervals else 0.0
        top = max((v for _, v in self.speeds), default=0.0)
        return predicted, size / 2 + cfg.gate_m + top * max(unseen, 0.0)

    def _follow(self, points: np.ndarray, T: np.ndarray, stamp_ns: int
                ) -> tuple[np.ndarray, np.ndarray] | str:
        """The cluster nearest where the track predicts the object and the points near there
        (before the density filter), world; or why none."""
        cfg = self.cfg
        predicted, radius = self._region(stamp_ns, self.intervals)
        centre_cam = (predicted - T[:3, 3]) @ T[:3, :3]  # predicted centre in the camera frame
        offset = points - centre_cam
        near = np.einsum("ij,ij->i", offset, offset) < radius**2
        world = self._above_seabed(to_world(points[near], T))
        dense, spacing = surface_points(world, cfg)
        found = clusters(dense, cfg.cluster_eps_spacings * max(spacing, 1e-3))
        big = [c for c in found if len(c) >= cfg.min_object_points]
        if not big:
            return "object not found near its track"
        nearest = min(big, key=lambda q: np.linalg.norm(q.mean(axis=0) - predicted))
        return joined(nearest, found, cfg.join_m, cfg.join_min_width_m), world

    def _predicted(self, stamp_ns: int, intervals: deque[float]) -> np.ndarray:
        """Where the track puts the object at ``stamp_ns``: the parabola through its last
        three centroids (a line through two), at most one frame interval past the last.

        A swing turns back: the straight line from a smoothed velocity put a 13 cm sphere
        swinging 0.3 m at 2.5 s, seen at 5 Hz, 12-13 cm off at every turn, and ran on away
        from it while it went unseen (30-60 cm off: lost for 3-4 frames of every swing,
        random-97-006). Beyond a frame the search grows with the time unseen instead."""
        assert self.track is not None
        if len(self.fits) < 2:
            return self.track
        ts = np.array([t for t, _ in self.fits]) - self.fits[-1][0]
        ps = np.array([p for _, p in self.fits])
        frame = float(np.median(intervals)) if intervals else 0.0
        tau = min(max(stamp_ns * 1e-9 - self.fits[-1][0], 0.0), frame)
        coef = np.linalg.solve(np.vander(ts), ps)  # exact through them: distinct stamps
        return np.vander([tau], len(ts))[0] @ coef

    def _above_seabed(self, world: np.ndarray) -> np.ndarray:
        if self.seabed is None or not len(world):
            return world
        return world[world @ self.seabed[:3] + self.seabed[3] > self.cfg.seabed_distance_m]

    def _update_track(self, fit: ShapeFit, stamp_ns: int) -> None:
        if self.track is not None and stamp_ns > self.last_stamp_ns:
            step = (fit.centre - self.track) / ((stamp_ns - self.last_stamp_ns) * 1e-9)
            self.speeds.append((stamp_ns, float(np.linalg.norm(step))))
            while self.speeds[0][0] < stamp_ns - self.cfg.speed_memory_s * 1e9:
                self.speeds.popleft()
        else:
            self.fits.clear()
        self.fits.append((stamp_ns * 1e-9, fit.centre))
        self.track, self.last_stamp_ns, self.misses = fit.centre, stamp_ns, 0
        # A box's axes in the learnt shape's order: those of a fit made with it.
        self.axis, self.frame = fit.axis, fit.frame if self.prior is not None else None
        if self.prior is None:
            self.learnt.append(fit)
            if len(self.learnt) >= self.cfg.learn_frames:
                self.prior = learnt_shape(self.learnt)


def axial_span(points: np.ndarray, fit: ShapeFit) -> tuple[float, float] | None:
    """Where the object ends along the fit's axis, metres from its centre (lower, upper):
    the fitted shape's ends or, where they reach farther, its points' (1st and 99th
    percentiles: a stray is no end). A bottle's neck is no part of the cylinder fitted to
    its body, but its points are the object's: a 31 cm bottle's fit ended 8 cm short of its
    neck, and the arm's palm met it there. None for a sphere or box.

    points : array, shape (n, 3), metres, the frame of the fit
    """
    if fit.shape not in ("cylinder", "revolution"):
        return None
    h = (points - fit.centre) @ fit.axis
    lo, hi = np.percentile(h, [1.0, 99.0])
    return (min(float(lo), fit.offset - fit.length / 2),
            max(float(hi), fit.offset + fit.length / 2))


def consistent_with(fit: ShapeFit, fits: list[ShapeFit], tolerance: float = 0.1) -> bool:
    """While the shape is being learnt: do ``fit``'s sizes match the median of earlier fits?

    A free fit of a partly hidden cylinder is short, and its centre is off by half of what is
    hidden; such a frame is not reported. The first three fits are taken as they come.
    """
    if len(fits) < 3:
        return True
    for size in ("radius", "length"):
        median = float(np.median([getattr(f, size) for f in fits]))
        value = getattr(fit, size)
        # A solid of revolution seen longer is seen more whole, not another shape: a bottle
        # hanging neck down, seen from above in its first frames, shows its base and body
        # only, and its neck when it swings (random-101-011: 7.6 cm, then 15.6).
        if size == "length" and fit.shape == "revolution" and value > median:
            continue
        if not same_size(value, median, tolerance):
            return False
    return True


def same_size(size: float, reference: float, tolerance: float = 0.1) -> bool:
    """Whether ``size`` (metres) is ``reference``'s, within ``tolerance`` of it or 1 cm."""
    return abs(size - reference) <= max(0.01, tolerance * reference)


def learnt_shape(fits: list[ShapeFit]) -> ShapeFit:
    """The shape most fits agreed on, with the median of their radii, lengths and RMS."""
    shapes = [f.shape for f in fits]
    shape = max(set(shapes), key=shapes.count)
    same = [f for f in fits if f.shape == shape]
    # The typical RMS, not the best: a later frame is judged against it (revolution.py,
    # max_rms_ratio), and against the best one frame in two of a 13 x 15 cm ellipsoid was
    # refused (1.6 mm against 0.83; the median 1.17).
    rms = float(np.median([f.rms for f in same]))
    best = replace(min(same, key=lambda f: f.rms), rms=rms)
    if shape == "box":
        return learnt_box(same, best)
    radius = float(np.median([f.radius for f in same]))
    if shape == "revolution":
        return learnt_revolution(same, replace(best, radius=radius))
    length = 2 * radius if shape == "sphere" else float(np.median([f.length for f in same]))
    return ShapeFit(shape=shape, centre=best.centre, axis=best.axis, radius=radius,
                    length=length, rms=rms, inliers=best.inliers, sigma=best.sigma)


def learnt_revolution(fits: list[ShapeFit], best: ShapeFit) -> ShapeFit:
    """A solid of revolution's length, the upper quartile of the fits' (:func:`_upper`: a
    seen outline falls short of a hidden end, never long but by noise), and where along
    it the volume centre lies (``offset``), the median over the fits that saw about that
    length, and the outline of the one of them nearest its points: with them a view that
    sees only one end's flat face, or a part of the outline, still places the centre
    (:func:`~wavegrasp.perception.revolution.fit_revolution`)."""
    length = _upper([f.length for f in fits])
    whole = [f for f in fits if same_size(f.length, length)]
    offset = float(np.median([f.offset for f in whole])) if whole else best.offset
    outline = min(whole, key=lambda f: f.rms).outline if whole else best.outline
    return replace(best, length=length, offset=offset, outline=outline)


#: learnt_box: a seen extent is short by up to a row of the face along it, long only by noise.
SIZE_PERCENTILE = 75
#: learnt_box: extents this far from their median (a share of it) are another axis's.
SIZE_OUTLIER = 0.25


def _upper(v: list[float]) -> float:
    """The upper quartile of extents ``v`` (metres) within SIZE_OUTLIER of their median: a
    frame whose axes were matched wrongly gives another axis's extent (a 4 cm side seen as
    29 cm in 4 frames of 17), which the median ignores and an upper quartile would not."""
    a = np.asarray(v)
    off = np.abs(a - float(np.median(a)))
    # Of an even count the median may lie between two far apart: then those nearest it.
    near = off <= max(SIZE_OUTLIER * float(np.median(a)), off.min())
    return float(np.percentile(a[near], SIZE_PERCENTILE))


def learnt_box(fits: list[ShapeFit], best: ShapeFit) -> ShapeFit:
    """A box's sizes: per axis of ``best``'s frame, the upper quartile over the fits that saw
    that extent whole (each fit's axes matched to ``best``'s by direction). Not the median:
    the far edge of a face seen at a grazing angle falls up to a row short (26 mm on the top
    of a box 1.2 m from a 256-pixel camera 15 degrees above it), and the median of a 9 cm
    depth was learnt 12 mm short, the centroid 6 mm off in every frame after (:func:`_upper`)."""
    assert best.frame is not None
    seen: list[list[float]] = [[], [], []]
    for f in fits:
        assert f.frame is not None and f.size is not None and f.whole is not None
        match = np.argmax(np.abs(best.frame.T @ f.frame), axis=1)
        for k in range(3):
            if f.whole[match[k]]:
                seen[k].append(float(f.size[match[k]]))
    size = np.array([_upper(v) if v else best.size[k] for k, v in enumerate(seen)])
    long = int(np.argmax(size))
    return replace(best, size=size, radius=float(np.hypot(*np.delete(size, long))) / 2,
                   length=float(size[long]))

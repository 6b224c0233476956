"""Fit a sphere or a finite cylinder to a one-sided noisy point cloud; return its volume centre.

The points' centroid is biased towards the camera by about half the radius; the fits model the
surface instead: least squares on point-to-surface distances, robust (Cauchy loss) first, then plain
on the inliers (|residual| < max(3 sigma, 3 mm)). A short Gauss-Newton loop does it: scipy's
least_squares agrees, but its overhead (0.2-0.5 ms a call) would use up the per-frame budget.
`points` and `viewpoint` share one frame (normally `world`, z up); results come back in it.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import open3d as o3d
from scipy.spatial import cKDTree

MIN_THRESHOLD = 0.003  # metres: points farther than this (or 3 sigma) from the surface are outliers
ROBUST_SCALE = 0.002  # metres: the Cauchy loss is quadratic below this residual, flat far above
CAP_MIN_POINTS = 8  # a flat end needs this many points to set the end's position by itself
END_MARGIN = 0.005  # metres: the wall refit leaves out points this close to an end (cap rims)
#: metres: a fit this near the points is never judged far off them against a learnt fit (a
#: noise-free or very fine cloud's learnt fits are a few tenths of a millimetre off, and a
#: ratio of such is no sign of a wrong axis or a partial view)
RMS_FLOOR_M = 0.001
GAP = 15.0  # mean point spacings (and >= 5 mm): a wider gap along the axis splits off strays
#: metres: points spread less than this across their length (standard deviation) are a line,
#: not a surface: the tether's 1.6 mm, a 4.8 cm bottle neck's 7-8 mm
LINE_WIDTH_M = 0.004

Model = Callable[[np.ndarray, np.ndarray], tuple[np.ndarray, np.ndarray]]


@dataclass(frozen=True)
class ShapeFit:
    """One fitted object, in the frame of the points; lengths in metres."""

    shape: str  # "sphere", "cylinder" or "box"
    centre: np.ndarray  # shape (3,), the volume centroid
    axis: np.ndarray  # shape (3,), unit, the cylinder's (box's longest) axis, axis[2] >= 0;
    # (0, 0, 1) for a sphere
    radius: float
    length: float  # 2 * radius for a sphere
    rms: float  # RMS of the inliers' point-to-surface residuals
    inliers: np.ndarray  # shape (n,), bool, the points explained by the fitted surface
    sigma: float  # sqrt(trace(cov)): RMS of the 3-D centre error (each axis' std is below it)
    cov: np.ndarray | None = None  # shape (3, 3), square metres, the centre's covariance
    frame: np.ndarray | None = None  # a box: shape (3, 3), its axes (columns)
    size: np.ndarray | None = None  # a box: shape (3,), metres, its extents along them
    whole: np.ndarray | None = None  # a box: shape (3,), bool, the extent seen whole
    #: metres along ``axis`` from the volume centre to the middle of its length: a bottle's
    #: neck moves its centre towards the body, so its ends are not equally far from it
    offset: float = 0.0
    #: a solid of revolution: shape (m, 2), metres, its outline: heights along ``axis`` from
    #: the volume centre (ascending) and the radius at each
    outline: np.ndarray | None = None

    def far_off(self, rms: float, ratio: float) -> bool:
        """Whether a fit ``rms`` metres off its points is far off next to this (learnt) fit:
        more than ``ratio`` times its RMS and more than RMS_FLOOR_M."""
        return rms > max(ratio * self.rms, RMS_FLOOR_M)


def segment_plane(points: np.ndarray, threshold: float, iterations: int = 200
                  ) -> tuple[np.ndarray, np.ndarray]:
    """The plane most ``points`` (shape (n, 3), metres) lie within ``threshold`` of, by
    open3d's RANSAC: plane (a, b, c, d), shape (4,), and its inliers' indices. The same
    points give the same plane: open3d draws its samples on all its threads from one seeded
    generator, in whatever order the threads come (measured: the same cloud gave boxes whose
    centroids differed by 0.3 mm in two processes, and lockstep runs that did not repeat),
    so it runs on one thread here, where 200 samples of a few thousand points take well
    under a millisecond anyway."""
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points.astype(np.float64)))
    threads = o3d.utility.get_max_threads()
    o3d.utility.set_max_threads(1)
    try:
        o3d.utility.random.seed(0)
        plane, inliers = pcd.segment_plane(threshold, 3, iterations)
    finally:
        o3d.utility.set_max_threads(threads)
    return np.asarray(plane), np.asarray(inliers, dtype=int)


def check_points(points: np.ndarray, min_points: int = 20) -> np.ndarray:
    """Return `points` as an array, shape (n, 3), float64; raise ValueError if unusable."""
    p = np.asarray(points, dtype=float)
    if p.ndim != 2 or p.shape[1] != 3:
        raise ValueError(f"points must have shape (n, 3), got {p.shape}")
    if not np.isfinite(p).all():
        raise ValueError("points contain NaN or inf")
    if len(p) < min_points:
        raise ValueError(f"need at least {min_points} points, got {len(p)}")
    return p


def check_vector(name: str, v: np.ndarray) -> np.ndarray:
    """Return `v` as an array, shape (3,), float64; raise ValueError unless finite, shape (3,)."""
    v = np.asarray(v, dtype=float)
    if v.shape != (3,) or not np.isfinite(v).all():
        raise ValueError(f"{name} must be a finite array of shape (3,), got {v!r}")
    return v


def check_sizes(**sizes: float | None) -> None:
    """Raise ValueError unless each of `sizes` (e.g. radius=...) is None or a finite number > 0."""
    for name, value in sizes.items():
        if value is not None and not (np.isfinite(value) and value > 0):
            raise ValueError(f"{name} must be None or a finite number > 0, got {value!r}")


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v)


#: A curved wall seen from the side shows its radius either side of its axis (a sphere's all
#: round the line of sight), less a rim the camera sees too obliquely: a fit wider than
#: RIM_RATIO times the points' spread across, plus RIM_SPACINGS of their spacing, is no
#: surface that was seen (measured on bottles and cylinders 0.5-1.5 m away: 1.1-1.74 times).
RIM_RATIO, RIM_SPACINGS = 1.5, 2.0
#: Viewed within this of its axis (cosine) a wall's rim is all round: nothing to check.
ALONG_VIEW_COS = 0.85


def wider_than_seen(points: np.ndarray, centre: np.ndarray, axis: np.ndarray | None,
                    viewpoint: np.ndarray, radius: float) -> str | None:
    """Why a curved surface of ``radius`` (metres) about ``centre`` (a sphere: ``axis``
    None) or about the axis through it along the unit ``axis`` is wider than the
    ``points`` (shape (n, 3), metres) seen from ``viewpoint`` spread across it, or None.

    A flat face's points lie on an arc of any large circle behind them: a 4.2 x 2.8 x 30 cm
    box 1.6 m from a 256 x 192 camera was fitted outlines of 4-25 cm radius and spheres of
    tens of metres, its points 2 cm either side of the axis; an outline beat its faces' RMS
    in one frame in three and it was learnt as a solid 14.8 cm across, wider than the jaw
    opens (random-151-020: its centroid 62 mm off, never grasped)."""
    view = _unit(centre - viewpoint)
    if axis is None:  # distance from the line of sight through the centre
        d = points - centre
        across = np.sqrt(np.maximum(np.einsum("ij,ij->i", d, d) - (d @ view) ** 2, 0.0))
    elif abs(float(view @ axis)) > ALONG_VIEW_COS:
        return None
    else:
        across = np.abs((points - centre) @ _unit(np.cross(axis, view)))
    seen = float(np.percentile(across, 98))
    if radius <= RIM_RATIO * seen:  # most fits: no need for the spacing (a tree, per frame)
        return None
    spacing = float(np.median(cKDTree(points).query(points, k=2)[0][:, 1]))
    if radius > RIM_RATIO * seen + RIM_SPACINGS * spacing:
        return (f"a surface {radius * 200:.1f} cm across, its points {seen * 200:.1f} cm "
                "(a flat face seen, no curved one)")
    return None


def line_width(q: np.ndarray) -> float:
    """How far points ``q`` (shape (n, 3), metres) spread across their longest direction:
    the standard deviation along their second principal direction, metres."""
    d = q - q.mean(axis=0)
    return float(np.sqrt(max(np.linalg.eigvalsh(d.T @ d / len(q))[1], 0.0)))


def noise_threshold(r: np.ndarray) -> float:
    """Residuals farther than this from the surface are outliers: 3 sigma of ``r`` (metres,
    the MAD's), at least MIN_THRESHOLD."""
    return max(3.0 * 1.4826 * float(np.median(np.abs(r - np.median(r)))), MIN_THRESHOLD)


def _solve(model: Model, x: np.ndarray, p: np.ndarray, robust: bool, tol: float) -> np.ndarray:
    """Minimise sum(loss(r)) over x by Gauss-Newton (reweighted if `robust`), halving steps
    until the cost drops; stop when the step is below `tol` or no step lowers the cost."""
    def cost(r):  # Cauchy or squares
        return np.sum(np.log1p((r / ROBUST_SCALE) ** 2)) if robust else r @ r
    r, J = model(x, p)
    for _ in range(30):
        Jw = J / (1 + (r / ROBUST_SCALE) ** 2)[:, None] if robust else J
        H = Jw.T @ J
        try:
            step = -np.linalg.solve(H + 1e-12 * np.trace(H) * np.eye(len(x)), Jw.T @ r)
        except np.linalg.LinAlgError:  # degenerate (e.g. a sphere's radius running away)
            break
        c0, t = cost(r), 1.0
        while t > 0.05:
            rt, Jt = model(x + t * step, p)
            if cost(rt) <= c0:
                break
            t /= 2
        else:  # no descent along the step: converged as far as it can
            break
        x, r, J = x + t * step, rt, Jt
        if np.linalg.norm(t * step) < tol:
            break
    return x


def _cov(J: np.ndarray, r: np.ndarray) -> np.ndarray:
    return float(r @ r) / max(len(r) - J.shape[1], 1) * np.linalg.pinv(J.T @ J)


def _fit(model: Model, x: np.ndarray, p: np.ndarray, select=lambda x, inl: inl):
    """Robust fit on all points, plain refit on `select(x, inliers)`; return x, r, J, inliers."""
    r = model(x := _solve(model, x, p, True, 1e-4), p)[0]
    inl = np.abs(r) < noise_threshold(r)
    use = select(x, inl) if inl.sum() >= 2 * len(x) else np.ones(len(p), bool)
    r, J = model(x := _solve(model, x, p[use], False, 1e-7), p)
    return x, r, J, np.abs(r) < noise_threshold(r[use])


def fit_sphere(points: np.ndarray, viewpoint: np.ndarray, radius: float | None = None) -> ShapeFit:
    """Fit a sphere (free radius, or `radius` in metres fixed) to points seen from `viewpoint`.

    points : array, shape (n, 3), metres; viewpoint : array, shape (3,), metres, same frame.
    The start is the points' median pushed away from the camera by about half a radius.
    """
    p, vp = check_points(points), check_vector("viewpoint", viewpoint)
    check_sizes(radius=radius)
    u, d = _unit((m := np.median(p, axis=0)) - vp), p - m
    lateral2 = np.einsum("ij,ij->i", d, d) - (d @ u) ** 2  # median about 0.6 r**2 (hemisphere)
    r0, free = radius or float(np.sqrt(np.median(lateral2) / 0.6)), radius is None

    def model(x, q):
        dist = np.sqrt(np.einsum("ij,ij->i", d := q - x[:3], d))
        J = np.full((len(q), 4 if free else 3), -1.0)  # d residual / dR = -1
        J[:, :3] = -d / dist[:, None]
        return dist - (x[3] if free else radius), J

    x, r, J, inl = _fit(model, np.append(m + 0.6 * r0 * u, r0)[: 4 if free else 3], p)
    cov, R = _cov(J[inl], r[inl])[:3, :3], float(x[3]) if free else float(radius)
    return ShapeFit("sphere", x[:3], np.array([0.0, 0.0, 1.0]), R, 2 * R,
                    float(np.sqrt(np.mean(r[inl] ** 2))), inl, float(np.sqrt(np.trace(cov))), cov)


def _wall_model(base: np.ndarray, a0: np.ndarray, radius: float | None):
    """Return the wall's model, x = (s, t, alpha, beta[, R]), and its basis e1, e2: the axis
    passes through base + s e1 + t e2 along a0 + alpha e1 + beta e2 (normalised)."""
    e1 = _unit(np.cross(a0, [1.0, 0.0, 0.0] if abs(a0[0]) < 0.9 else [0.0, 1.0, 0.0]))
    E, k = np.column_stack([e1, e2 := np.cross(a0, e1)]), 5 if radius is None else 4

    def model(x, q):
        nu = np.linalg.norm(u := a0 + x[2] * e1 + x[3] * e2)
        h = (d := q - (base + x[0] * e1 + x[1] * e2)) @ (u / nu)
        rho = np.sqrt(np.maximum(np.einsum("ij,ij->i", d, d) - h * h, 1e-18))
        n12 = (d @ E - h[:, None] * ((u / nu) @ E)) / rho[:, None]  # unit normal in e1, e2
        J = np.full((len(q), k), -1.0)  # d residual / dR = -1
        J[:, :2], J[:, 2:4] = -n12, n12 * (-h / nu)[:, None]
        return rho - (x[4] if radius is None else radius), J

    return model, e1, e2


def _wall_run(h: np.ndarray) -> np.ndarray:
    """Return the sorted axial coordinates `h` of the run without wide gaps around the median."""
    h = np.sort(h)
    spacing = (h[int(0.9 * len(h))] - h[int(0.1 * len(h))]) / (0.8 * len(h))
    cuts = np.flatnonzero(np.diff(h) > max(GAP * spacing, 0.005))
    lo, hi = cuts[cuts < len(h) // 2], cuts[cuts >= len(h) // 2]
    return h[(lo[-1] + 1 if len(lo) else 0):(hi[0] + 1 if len(hi) else len(h))]


def _end(h, rho, R, thr, sign, wall_end, h_mid, ok, wall_var) -> tuple[float, float]:
    """Return an end's axial position and variance (the flat end's points, well inside the
    radius, if enough, else the last wall point, variance `wall_var`); mark them in `ok`."""
    cap = (rho < R - thr) & (np.abs(h - wall_end) < max(thr, 0.004)) & (sign * (h - h_mid) > 0)
    if cap.sum() < CAP_MIN_POINTS:
        return float(wall_end), wall_var
    med = np.median(hc := h[cap])  # trimmed: a tether point just beyond the bottom end is left out
    keep = np.abs(hc - med) < max(3 * 1.4826 * np.median(np.abs(hc - med)), 0.0005)
    ok[np.flatnonzero(cap)[keep]] = True
    return float(hc[keep].mean()), float(hc[keep].var() / keep.sum()) + 1e-8


def _partial_view(top: float, v_top: float, bottom: float, v_bot: float, wall_var: float,
                  length: float) -> tuple[float, float, float]:
    """Axial centre, its variance and length when the seen extent is shorter than ``length``."""
    top_cap, bottom_cap = v_top != wall_var, v_bot != wall_var
    if top_cap and not bottom_cap:
        return top - length / 2, v_top, length
    if bottom_cap and not top_cap:
        return bottom + length / 2, v_bot, length
    return (top + bottom) / 2, ((length - (top - bottom)) / 2) ** 2, length


def fit_cylinder(points: np.ndarray, viewpoint: np.ndarray, radius: float | None = None,
                 length: float | None = None, axis_hint: np.ndarray | None = None) -> ShapeFit:
    """Fit a finite cylinder to points seen from `viewpoint`; sizes in metres, None = free.

    points : array, shape (n, 3), metres; viewpoint, axis_hint : array, shape (3,), same frame.
    The wall (axis, radius) is fitted from `axis_hint` or the points' main axis, then refitted
    without the points near the ends (cap rims). An end is the trimmed mean of its flat end's
    points if CAP_MIN_POINTS are seen (the upper end, for a camera above), else the last wall
    point; the centre is their midpoint or, with `length`, the variance-weighted mean of
    top - length / 2 and bottom + length / 2. Tether points (near the axis) are neither.
    """
    p, vp = check_points(points), check_vector("viewpoint", viewpoint)
    check_sizes(radius=radius, length=length)
    dist = np.linalg.norm(p - (m := np.median(p, axis=0)), axis=1)
    near = p[dist <= 2.5 * np.median(dist)]  # without most of a tether
    d = near - near.mean(axis=0)  # the main axis of the points, unless hinted
    a0 = np.linalg.eigh(d.T @ d)[1][:, -1] if axis_hint is None else _unit(
        check_vector("axis_hint", axis_hint))
    v_perp = _unit((m - vp) - ((m - vp) @ a0) * a0)
    side = np.sort(near @ np.cross(a0, v_perp))  # across the line of sight: about +-r
    r0 = radius or float(side[int(0.975 * len(side))] - side[int(0.025 * len(side))]) / 1.9
    base = m + 0.75 * r0 * v_perp
    model, e1, e2 = _wall_model(base, a0, radius)

    def geometry(x, inl):  # axis point and direction, axial coordinates, wall run, wall points
        c_line, a = base + x[0] * e1 + x[1] * e2, _unit(a0 + x[2] * e1 + x[3] * e2)
        h = (p - c_line) @ a
        hw = _wall_run(h[inl])
        wall = inl & (h > hw[0] + END_MARGIN) & (h < hw[-1] - END_MARGIN)
        return c_line, a, h, hw, (wall if wall.sum() >= 2 * len(x) else inl)

    x0 = np.array([0.0, 0.0, 0.0, 0.0, r0][: 5 if radius is None else 4])
    x, r, _, inl = _fit(model, x0, p, lambda x, inl: geometry(x, inl)[-1])
    c_line, a, h, hw, wall = geometry(x, inl)
    R = float(x[4]) if radius is None else float(radius)
    a, h, hw = (a, h, hw) if a[2] >= 0 else (-a, -h, -hw[::-1])
    r, rho = r[wall], np.linalg.norm(p - c_line - h[:, None] * a, axis=1)
    thr, spacing = noise_threshold(r), (hw[-1] - hw[0]) / len(hw)  # spacing: gap at a wall end
    view_a = max(abs(_unit(c_line - vp) @ a), 0.3)
    ok, wall_var = inl.copy(), spacing**2 + float(np.mean(r**2)) * view_a**2
    (top, v_top), (bottom, v_bot) = (_end(h, rho, R, thr, sign, end, hw[len(hw) // 2], ok, wall_var)
                                     for sign, end in ((1.0, hw[-1]), (-1.0, hw[0])))
    if length is not None and top - bottom < length - max(0.008, 3 * thr):
        # Part of the object is hidden (a dropout, the frame's edge): a seen cap is a true end,
        # an edge of the hole is not. With no cap, the centre could lie anywhere along the gap.
        hc, v_axial, L = _partial_view(top, v_top, bottom, v_bot, wall_var, float(length))
    elif length is not None:  # the variance-weighted mean of the two ends' estimates
        hc = (v_bot * (top - length / 2) + v_top * (bottom + length / 2)) / (v_top + v_bot)
        v_axial, L = v_top * v_bot / (v_top + v_bot), float(length)
    else:
        hc, v_axial, L = (top + bottom) / 2, (v_top + v_bot) / 4, float(top - bottom)
    centre = c_line + hc * a
    model_c, e1, e2 = _wall_model(centre, a, radius)  # across the axis: Jacobian at the centre
    E = np.column_stack([e1, e2])
    cov = E @ _cov(model_c(np.array([0, 0, 0, 0, R]), p[wall])[1], r)[:2, :2] @ E.T
    cov += v_axial * np.outer(a, a)
    return ShapeFit("cylinder", centre, a, R, L, float(np.sqrt(np.mean(r**2))), ok,
                    float(np.sqrt(np.trace(cov))), cov)

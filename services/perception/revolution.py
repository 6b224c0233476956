"""Fit a solid of revolution of unknown outline (an ellipsoid, a bottle with a neck) to a
one-sided noisy point cloud; return its volume centre.

The axis is the line about which the points' distances are the same at every height: each
point's distance from the outline (the mean distances of slices ``SLICE_M`` thick, joined by
straight lines), measured across the outline, is the residual, minimised by Gauss-Newton
over the line's four parameters (a numerical Jacobian: four columns). The outline is then
the slices' mean distances, and the volume centre lies on the axis at the centroid of the
solid that outline sweeps (frusta summed), so a neck or a tapering end moves it as it moves
the object's mass.
A sphere or cylinder fit of such objects is off by 7-73 mm (measured); its faceless sides and
ends are seen as they are, so no part of the outline is assumed. A flat end (a bottle's base)
is no part of the wall: its points are measured from its plane (:func:`end_faces`).
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from wavegrasp.perception.fit import (
    MIN_THRESHOLD,
    ShapeFit,
    _unit,
    check_points,
    check_vector,
    wider_than_seen,
)
from wavegrasp.wavetank.body import solid_of_revolution

SLICE_M = 0.004  # slice thickness along the axis, metres
MIN_SLICE_POINTS = 3  # a slice with fewer points has no radius of its own
END_FACE_COS = 0.9  # a surface whose normal is this near the axis faces along it: an end
NORMAL_NEIGHBOURS = 10  # points a surface normal is estimated from
FLAT_M = 0.0015  # an end bulging no more than this over its width is a face
FACE_MIN_POINTS, FACE_MIN_SHARE = 20, 0.1  # a face holds this many and this share of points
MAX_GAP_M = 0.05  # slices farther apart along the axis than this are not one object's
LONE_SLICES = 5  # a slice with no other this many slices near is strays' (_main_run)
#: An axis this near as good as the best, fitted from up, is taken: a tethered object hangs
#: along its tether, and a flat ellipsoid seen from the side fits as well lying across the
#: view, its depth taken for its height (random-7-011: 10.6 x 7.5 cm, its centroid 16 mm
#: near; one frame in five fitted upright, as near the points).
UP_TIE = 1.15
FAR_OFF = 1.5  # a fit more than this times the learnt RMS off its points is a wrong one


def _frame(a: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    e1 = _unit(np.cross(a, [1.0, 0.0, 0.0] if abs(a[0]) < 0.9 else [0.0, 1.0, 0.0]))
    return e1, np.cross(a, e1)


def _line(x: np.ndarray, base: np.ndarray, a0: np.ndarray, e1: np.ndarray, e2: np.ndarray):
    return base + x[0] * e1 + x[1] * e2, _unit(a0 + x[2] * e1 + x[3] * e2)


def normals(p: np.ndarray) -> np.ndarray:
    """Unit surface normals (unsigned), shape (n, 3), of points ``p`` (shape (n, 3)): the
    least principal direction of each point's NORMAL_NEIGHBOURS nearest."""
    _, nn = cKDTree(p).query(p, k=min(NORMAL_NEIGHBOURS, len(p)))
    q = p[nn] - p[nn].mean(axis=1, keepdims=True)
    return np.linalg.eigh(np.einsum("nki,nkj->nij", q, q))[1][:, :, 0]


def end_faces(p: np.ndarray, n: np.ndarray, c: np.ndarray, a: np.ndarray) -> np.ndarray:
    """Which points lie on a flat end of the object about the axis through ``c`` along the
    unit ``a``: 1 the upper end's, 2 the lower's, 0 the wall's. p, n : arrays, shape (n, 3),
    the points and their normals.

    A flat end (a bottle's base) lies across the axis, its points at every distance from it:
    counted in its slice's mean, a bottle's 268 base points pulled the axis 25 mm away from
    the camera and its radius from 54 to 80 mm (the axis farther off spreads their distances
    less). Points whose normal lies within END_FACE_COS of the axis, at the upper or lower
    end, are that end's if they bulge by no more than FLAT_M: a flat ellipsoid's or a
    sphere's cap is no plane (taken for an end, a 12 x 8 cm ellipsoid's centroid came out
    4 mm off). And only if they are enough to tell: a dozen points of a 13 cm ellipsoid's
    pole bulged 0-5 mm, and taken for a face in one frame in three they put its centroid
    2.7 mm low. Decided once, about an axis fitted without ends: decided anew for every axis
    tried, a tilted axis made a 10 cm cylinder's near wall an end, its outline 12 mm long."""
    h = (p - c) @ a
    end = np.zeros(len(p), int)
    across = np.abs(n @ a) >= END_FACE_COS
    upper = h > h.mean()
    for label, on in ((1, across & upper), (2, across & ~upper)):
        if on.sum() >= max(FACE_MIN_POINTS, FACE_MIN_SHARE * len(p)) and _sag(
                p[on] - c, a) <= FLAT_M:
            end[on] = label
    return end


def _sag(d: np.ndarray, a: np.ndarray) -> float:
    """How far a patch of points ``d`` (shape (n, 3), metres) facing along the unit ``a``
    bulges over its width, metres: h = c0 + c1 x + c2 y + c3 (x² + y²) fitted across ``a``
    (the linear terms take up a tilted or offset axis), and |c3| times its half-width
    squared."""
    e1, e2 = _frame(a)
    x, y = d @ e1, d @ e2
    A = np.column_stack([np.ones(len(d)), x, y, x * x + y * y])
    c3 = np.linalg.lstsq(A, d @ a, rcond=None)[0][3]
    return float(abs(c3) * (max(np.ptp(x), np.ptp(y)) / 2) ** 2)


def _slices(p: np.ndarray, c: np.ndarray, a: np.ndarray, end: np.ndarray):
    """Heights, distances, slice index per point, each slice's mean distance over its wall
    points and their count, and each end point's height above its end's plane (its points'
    mean; NaN for the wall's). ``end``: :func:`end_faces`."""
    d = p - c
    h = d @ a
    rho = np.sqrt(np.maximum(np.einsum("ij,ij->i", d, d) - h * h, 0.0))
    k = np.floor((h - h.min()) / SLICE_M).astype(int)
    ends = np.full(len(h), np.nan)
    for label in (1, 2):
        on = end == label
        if on.any():
            ends[on] = h[on] - h[on].mean()
    wall = end == 0
    count = np.bincount(k, weights=wall.astype(float)).astype(int)
    med = np.bincount(k, weights=rho * wall) / np.maximum(count, 1)
    return h, rho, k, med, count, ends


def _off_outline(h: np.ndarray, rho: np.ndarray, k: np.ndarray, med: np.ndarray,
                 count: np.ndarray, ends: np.ndarray) -> np.ndarray:
    """Each point's distance from the outline (the slices' mean distances joined by straight
    lines), across it: where the outline slopes, as near an ellipsoid's pole, a distance
    along the radius overstates it, and a slice 4 mm thick spans millimetres of radius: an
    oblate ellipsoid's true axis then left more residual than a wrong one (measured 1.39
    against 1.31 mm), and was not chosen. Zero for points of slices too sparse to say. An
    end's points are measured from the end's plane (``ends``, :func:`_slices`), so a flat
    base is as near its points as a wall is."""
    ok, wall = count >= MIN_SLICE_POINTS, np.isnan(ends)
    if ok.sum() < 2:
        return np.where(wall, np.where(ok[k], rho - med[k], 0.0), ends)
    # The outline through the slices' centres, sparse slices bridged; each point read on the
    # segment between the two centres about it (indexing: a search per point was 3x slower).
    used = np.flatnonzero(ok)
    outline = np.interp(np.arange(len(med)), used, med[used])
    u = (h - h.min()) / SLICE_M - 0.5
    j = np.minimum(np.maximum(np.floor(u).astype(int), 0), len(med) - 2)
    w = np.minimum(np.maximum(u - j, 0.0), 1.0)
    slope = (outline[j + 1] - outline[j]) / SLICE_M
    r = (rho - outline[j] - w * (outline[j + 1] - outline[j])) / np.sqrt(1.0 + slope**2)
    return np.where(wall, np.where(ok[k], r, 0.0), ends)


def _residual(x, p, end, base, a0, e1, e2) -> np.ndarray:
    c, a = _line(x, base, a0, e1, e2)
    return _off_outline(*_slices(p, c, a, end))


def _fit_line(p: np.ndarray, end: np.ndarray, base: np.ndarray, a0: np.ndarray
              ) -> tuple[np.ndarray, float]:
    e1, e2 = _frame(a0)
    x, eps = np.zeros(4), np.array([1e-4, 1e-4, 1e-3, 1e-3])
    r = _residual(x, p, end, base, a0, e1, e2)
    for _ in range(15):
        J = np.column_stack([(_residual(x + e, p, end, base, a0, e1, e2) - r) / e[i]
                             for i, e in enumerate(np.diag(eps))])
        step = -np.linalg.lstsq(J, r, rcond=None)[0]
        t = 1.0
        while t > 0.05:
            rt = _residual(x + t * step, p, end, base, a0, e1, e2)
            if rt @ rt <= r @ r:
                break
            t /= 2
        else:
            break
        x, r = x + t * step, rt
        if np.linalg.norm(t * step) < 1e-6:
            break
    return x, float(np.sqrt(np.mean(r**2)))


def _inliers(p: np.ndarray, end: np.ndarray, c: np.ndarray, a: np.ndarray) -> np.ndarray:
    """The points within 3 standard deviations (at least MIN_THRESHOLD) of the outline."""
    h, rho, k, med, count, ends = _slices(p, c, a, end)
    r = _off_outline(h, rho, k, med, count, ends)
    return (np.abs(r) < max(3 * float(np.std(r)), MIN_THRESHOLD)) & _main_run(count)[k]


def _main_run(count: np.ndarray) -> np.ndarray:
    """Which slices belong to the object: of the runs of slices with MIN_SLICE_POINTS wall
    points and gaps of at most MAX_GAP_M (a bottle's hidden shoulder), the one with the most
    points. Three points of a tether 18 cm below an ellipsoid made a slice of their own,
    and the outline reached down to them (learnt 40 cm long, not 18). A slice with no other
    within LONE_SLICES is no part of it either: a tether's few points 3-5 cm below an
    ellipsoid's end made one, and the outline 5 cm longer than the object; such slices at
    the run's ends are left out."""
    used = np.flatnonzero(count >= MIN_SLICE_POINTS)
    while len(used) > 1 and used[1] - used[0] > LONE_SLICES:
        used = used[1:]
    while len(used) > 1 and used[-1] - used[-2] > LONE_SLICES:
        used = used[:-1]
    keep = np.zeros(len(count), bool)
    if not len(used):
        return keep
    runs = np.split(used, np.flatnonzero(np.diff(used) * SLICE_M > MAX_GAP_M) + 1)
    run = max(runs, key=lambda u: count[u].sum())
    keep[run] = True
    return keep


def _length_slack(length: float) -> float:
    """How far, metres, an outline seen may differ from one ``length`` metres long and be
    the same."""
    return max(2 * SLICE_M, 0.1 * length)


def _centre_from_face(h: np.ndarray, end: np.ndarray, a: np.ndarray, prior: ShapeFit,
                      wall: tuple[float, float]) -> float:
    """Where along the axis ``a`` (unit) the volume centre lies in a view that sees less
    than the ``prior``'s length: from the one flat end face it sees (a face is a true end;
    the edge of what is hidden is not) and the learnt distance from that end to the centre.

    h : array, shape (n,), metres, the points' heights along ``a``; end : their
    :func:`end_faces` labels (exactly one face seen); wall : the seen wall's lowest and
    highest heights. Raises ValueError for a wall reaching past the learnt length.
    """
    up = 1.0 if a[2] >= 0 else -1.0  # the learnt offset is along the upward axis
    label = 1 if (end == 1).any() else 2
    face = float(h[end == label].mean())
    top = (label == 1) == (up > 0)
    mid = face - up * (prior.offset + (0.5 if top else -0.5) * prior.length)
    ends = sorted(mid + up * (prior.offset + k * prior.length / 2) for k in (-1.0, 1.0))
    slack = _length_slack(prior.length)
    if wall[0] < ends[0] - slack or wall[1] > ends[1] + slack:
        raise ValueError("the outline reaches beyond the learnt one from its end face")
    return mid


#: _centre_from_outline: the shifts tried, metres apart
SHIFT_STEP_M = SLICE_M / 8


def _centre_from_outline(z: np.ndarray, r: np.ndarray, a: np.ndarray, prior: ShapeFit
                         ) -> tuple[float, float]:
    """Where along the axis ``a`` (unit) the volume centre lies in a view that sees less
    than the ``prior``'s length and no one flat end: where the seen part of the outline
    fits the learnt outline best, slid along the axis; and how uncertain that is (metres,
    one standard deviation). A 28 cm bottle seen 18-25 cm of its length, its base turned
    away from the camera, was refused in half its frames (random-199-028), though its neck
    and shoulder say where along it the view lies.

    z, r : arrays, shape (m,), metres: the seen slices' heights along ``a`` and their
    radii. The uncertainty is a quarter of the span of every shift whose sum of squares is
    within two of its chance fluctuations of the best's (1 + 2 sqrt(2 / (m - 1)) times
    it: a sum of m squared noises varies by sqrt(2 m) of their variance), near or far: a
    cylinder's wall fits a straight body anywhere along it, and the centre it gives is as
    uncertain as the body is long (with 4 sigma² alone, the learnt outline's own noise
    picked one shift: sigma 6.5 mm for a 12 cm view of a 24 cm body). Raises ValueError
    for an outline reaching past the learnt one wherever it is slid.
    """
    if prior.outline is None:
        raise ValueError(f"the outline is {np.ptp(z) * 100:.1f} cm long, the one learnt "
                         f"{prior.length * 100:.1f} cm (a partial view)")
    up = 1.0 if a[2] >= 0 else -1.0  # the learnt outline is along the upward axis
    zu = up * z
    hp, rp = prior.outline.T
    slack = _length_slack(prior.length)
    lo, hi = zu.max() - hp[-1] - slack, zu.min() - hp[0] + slack
    if hi < lo:
        raise ValueError(f"the outline is {np.ptp(z) * 100:.1f} cm long, longer than the "
                         f"one learnt ({prior.length * 100:.1f} cm) allows")
    shifts = np.arange(lo, hi + SHIFT_STEP_M / 2, SHIFT_STEP_M)
    sse = ((r - np.interp(zu[None, :] - shifts[:, None], hp, rp)) ** 2).sum(axis=1)
    best = int(np.argmin(sse))
    near = shifts[sse <= sse[best] * (1.0 + 2.0 * np.sqrt(2.0 / max(len(z) - 1, 1)))]
    return up * float(shifts[best]), (float(np.ptp(near)) + SHIFT_STEP_M) / 4


def fit_revolution(points: np.ndarray, viewpoint: np.ndarray,
                   prior: ShapeFit | None = None) -> ShapeFit:
    """Fit a solid of revolution to points seen from ``viewpoint``; with ``prior``, start from
    its axis. points : array, shape (n, 3), metres; viewpoint : shape (3,), same frame.

    The fit's ``radius`` is the outline's largest, ``length`` its extent along the axis and
    ``offset`` how far along the axis the middle of that extent lies from the volume centre.
    """
    p, vp = check_points(points), check_vector("viewpoint", viewpoint)
    d = p - p.mean(axis=0)
    principal = list(np.linalg.eigh(d.T @ d)[1].T)
    n = normals(p)
    if prior is None:
        # Starts: the points' principal directions, up (a tethered object hangs near it),
        # and the normals' main direction (a flat end's, where one holds most points).
        return _fit(p, n, vp, None, [*principal, np.array([0.0, 0.0, 1.0]),
                                     np.linalg.eigh(n.T @ n)[1][:, -1]])
    try:
        return _fit(p, n, vp, prior, [prior.axis])
    except ValueError:
        # A bottle in a 33 cm sea seen at 5 Hz turned 41 degrees between frames; from the
        # last frame's axis the fit ended 6 mm off its points or wider than they spread,
        # from the points' longest direction 0.5 mm off the true centre (random-199-028:
        # half its frames refused).
        return _fit(p, n, vp, prior, principal)


def _fit(p: np.ndarray, n: np.ndarray, vp: np.ndarray, prior: ShapeFit | None,
         axes: list[np.ndarray]) -> ShapeFit:
    """fit_revolution from the start ``axes``; ``n``: the points' :func:`normals`."""
    no_ends = np.zeros(len(p), int)  # every point the wall's: the axis before faces
    m = np.median(p, axis=0)
    d = p - p.mean(axis=0)
    best = None
    for a0 in axes:
        a0 = _unit(np.asarray(a0, dtype=float))
        v_perp = _unit((m - vp) - ((m - vp) @ a0) * a0)
        across = np.ptp(d @ np.cross(a0, v_perp)) / 2
        base = m + 0.75 * across * v_perp
        x, rms = _fit_line(p, no_ends, base, a0)
        # A flat end facing the camera may hold most of the points (a bottle's base seen
        # from above): counted as wall, no axis through it fits, so the start's own ends
        # are tried too.
        start_ends = end_faces(p, n, base, a0)
        if start_ends.any():
            x_e, rms_e = _fit_line(p, start_ends, base, a0)
            if rms_e < rms:
                x, rms = x_e, rms_e
        if a0[2] > 0.999:  # up: see UP_TIE
            rms /= UP_TIE
        if best is None or rms < best[0]:
            best = (rms, x, base, a0)
    assert best is not None
    _, x, base, a0 = best
    c, a = _line(x, base, a0, *_frame(a0))
    end = end_faces(p, n, c, a)
    if end.any():
        c, a = _line(_fit_line(p, end, c, a)[0], c, a, *_frame(a))
    inliers = _inliers(p, end, c, a)  # refit without strays (a tether's points, snow)
    c, a = _line(*_fit_line(p[inliers], end[inliers], c, a)[:1], c, a, *_frame(a))
    inliers = _inliers(p, end, c, a)
    h, rho, k, med, count, ends = _slices(p[inliers], c, a, end[inliers])
    r = _off_outline(h, rho, k, med, count, ends)
    used = np.flatnonzero(count >= MIN_SLICE_POINTS)
    if len(used) < 3:
        raise ValueError("too few slices along the axis for an outline")
    z = h.min() + (used + 0.5) * SLICE_M
    z = np.concatenate([[z[0] - SLICE_M / 2], z, [z[-1] + SLICE_M / 2]])
    outline = np.concatenate([[med[used[0]]], med[used], [med[used[-1]]]])
    length = float(z[-1] - z[0])
    mid = z[0] + solid_of_revolution(z, outline)[1]
    offset = (z[0] + z[-1]) / 2 - mid
    # Only a shorter view hides part of what was learnt; a longer one sees more of the
    # object than the learning frames did (a 9.2 cm ellipsoid learnt 7.6 cm from above,
    # then seen 8.4-8.8 cm as it swung: random-127-001, 517 frames refused) and is fitted
    # as it is.
    along = 0.0  # metres, how uncertain the centre is along the axis beyond the slices'
    if prior is not None and prior.length - length > _length_slack(prior.length):
        faces = [label for label in (1, 2) if (end[inliers] == label).any()]
        if len(faces) == 1:
            mid = _centre_from_face(h, end[inliers], a, prior, (z[0], z[-1]))
        else:
            mid, along = _centre_from_outline(z[1:-1], outline[1:-1], a, prior)
        length, offset = prior.length, prior.offset * (1.0 if a[2] >= 0 else -1.0)
    if reason := wider_than_seen(p[inliers], c, a, vp, float(outline.max())):
        raise ValueError(reason)
    centre = c + mid * a
    if np.linalg.norm(centre - m) > np.ptp(p, axis=0).max():
        raise ValueError("the outline's centre falls outside the object (no solid of "
                         "revolution fits)")
    rms = float(np.sqrt(np.mean(r**2)))
    if prior is not None and prior.far_off(rms, FAR_OFF):
        raise ValueError(f"the outline is {rms * 1e3:.2f} mm off the points, the one learnt "
                         f"{prior.rms * 1e3:.2f} mm (a partial view)")
    # Across the axis as a wall fit's; along it, the outline's ends (a slice each).
    sigma = float(np.hypot(rms / np.sqrt(max(inliers.sum(), 1)) * 4, SLICE_M / 4))
    profile = np.column_stack([z - mid, outline])  # along a, from the volume centre
    if a[2] < 0:  # reported along the upward axis
        a, offset, profile = -a, -offset, profile[::-1] * [-1.0, 1.0]
    return ShapeFit("revolution", centre, a, float(outline.max()), length, rms,
                    inliers, float(np.hypot(sigma, along)), offset=float(offset),
                    outline=profile)

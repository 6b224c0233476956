"""Fit a box to a one-sided noisy point cloud from its flat faces; return its volume centre.

A camera sees one to three faces of a box. Each is found by RANSAC (open3d) and refitted by
least squares; the faces' normals give the box's axes. Along an axis whose face is seen, the
centre lies half the box's size behind that face (the face's position is set by hundreds of
points, so to a fraction of a millimetre); along an axis whose two faces are both hidden, the
centre is the middle of the seen faces' extent along it. Sizes come from the extents of frames
that see the whole of an axis (a face parallel to it is seen), learnt over the first frames
from every point near the object, those the density filter drops included: a face seen
obliquely is sampled in sparse rows that the filter takes for specks, and without them its
far part was lost (an 11.4 cm side learnt as 7.3 cm, the centroid 20 mm off; the points near
the object after learning are the filtered ones, as the stray points the filter drops could
stretch a single frame's extents).
A sphere or cylinder fit of a box never settled (an 8 x 5 x 15 cm box was never observed).
"""

from __future__ import annotations

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import ConvexHull, QhullError, cKDTree

from wavegrasp.perception.fit import (
    LINE_WIDTH_M,
    MIN_THRESHOLD,
    ShapeFit,
    check_points,
    check_vector,
    line_width,
    noise_threshold,
    segment_plane,
)

FACE_MIN_POINTS = 12  # a face needs this many points (and 3 % of the object's) to count
SQUARE = 0.25  # |cos| between two faces' normals above this: not two faces of one box
EDGE_ROWS = 0.5  # see _edge_gap
FLAT = 0.85  # the fraction of the points on one face that makes a face-on view
NOISE_SLAB = 0.012  # metres: the residuals the noise is measured on (the edges' other faces out)
LONGER = 0.5  # a seen extent this much longer than the learnt size is another side's
TRIM = 0.005  # the fraction of points left out at each end of an extent (edge noise)
SIDES_DIFFER = 0.2  # two sides this much apart in length are told apart by it (_one_face_axes)
LINK_SPACINGS = 2.5  # raw points this many point spacings apart are on one line (_with_raw)


class FaceOn(ValueError):
    """One flat face holds nearly all the points: the depth behind it cannot be seen, and a
    sphere or cylinder would fit the face (a plane is a cylinder of infinite radius).
    ``normal`` (shape (3,)) and ``offset`` (metres) are the face's plane: normal·x = offset."""

    def __init__(self, message: str, normal: np.ndarray, offset: float) -> None:
        super().__init__(message)
        self.normal, self.offset = normal, offset

    def rms(self, points: np.ndarray) -> float:
        """The face's plane's RMS off ``points`` (shape (n, 3), metres) within three sigmas
        of their residuals, as a shape fit's RMS is over its inliers."""
        r = points @ self.normal - self.offset
        return float(np.sqrt(np.mean(r[np.abs(r) < noise_threshold(r)] ** 2)))


def _plane(q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The least-squares plane of ``q`` (shape (n, 3)): its centroid and unit normal."""
    centre = q.mean(axis=0)
    return centre, np.linalg.eigh(np.cov((q - centre).T))[1][:, 0]


def _faces(p: np.ndarray, viewpoint: np.ndarray) -> list[tuple[np.ndarray, float, np.ndarray]]:
    """Up to three faces, each (unit normal out of the object, offset d: n·x = d on the face,
    indices of its points)."""
    left, faces, middle = np.arange(len(p)), [], p.mean(axis=0)
    while len(faces) < 3 and len(left) >= FACE_MIN_POINTS:
        idx = left[segment_plane(p[left], MIN_THRESHOLD)[1]]
        if len(idx) < max(FACE_MIN_POINTS, 0.03 * len(p)):
            break
        centre, n = _plane(p[idx])
        idx = idx[np.abs((p[idx] - centre) @ n) < MIN_THRESHOLD]
        centre = p[idx].mean(axis=0)
        behind = float(n @ (middle - centre))
        if abs(behind) > MIN_THRESHOLD:  # the object lies behind its every face
            n = n if behind < 0 else -n
        else:  # a face that holds nearly all the points: the camera is before it
            # (a face seen at a grazing angle was turned inside out by a 3 degree tilt of
            # its fitted normal, and the centre put a box's size off)
            n = n if n @ (viewpoint - centre) > 0 else -n
        left = np.setdiff1d(left, idx)
        if all(abs(n @ f[0]) < SQUARE for f in faces):
            faces.append((n, float(n @ centre), idx))
    return faces


def _grown(p: np.ndarray, faces: list) -> list[tuple[np.ndarray, float, np.ndarray]]:
    """The faces, each holding every point nearest its plane within three sigmas of the
    sensor's noise (measured on the first, largest face). The faces are found within
    MIN_THRESHOLD, which keeps a small face seen at a grazing angle from being taken into a
    large one; but a camera's depth noise grows with the square of the distance, and at 1.4 m
    (about 3 mm) such faces held two thirds of a box's points: too few for a box, and the
    thinned faces' rows made its edges uncertain (a 5 x 5 x 15 cm box 1.4 m away was observed
    in 1 % of frames)."""
    normals, offsets = np.array([f[0] for f in faces]), np.array([f[1] for f in faces])
    r = p @ normals.T - offsets  # signed distances, (n, faces)
    thr = noise_threshold(r[np.abs(r[:, 0]) < NOISE_SLAB, 0])
    dist = np.abs(r)
    nearest, within = dist.argmin(axis=1), dist.min(axis=1) < thr
    return [(n, d, np.flatnonzero(within & (nearest == j)))
            for j, (n, d, _) in enumerate(faces)]


def _rectangle_side(q: np.ndarray, normal: np.ndarray) -> np.ndarray:
    """A side of the smallest rectangle around the points ``q`` (shape (n, 3), metres) of a
    face with unit ``normal`` (shape (3,)), in its plane: a unit vector, shape (3,)."""
    u = np.cross(normal, np.eye(3)[int(np.argmin(np.abs(normal)))])
    u /= np.linalg.norm(u)
    v = np.cross(normal, u)
    xy = np.column_stack([q @ u, q @ v])
    try:
        hull = xy[ConvexHull(xy).vertices]
    except QhullError:  # the points on a line: that line is a side
        return np.linalg.eigh(np.cov((q - q.mean(axis=0)).T))[1][:, -1]
    edge = np.diff(np.vstack([hull, hull[:1]]), axis=0)
    angle = np.arctan2(edge[:, 1], edge[:, 0])
    c, s = np.cos(angle), np.sin(angle)
    along, across = hull @ np.vstack([c, s]), hull @ np.vstack([-s, c])  # (hull, edges)
    k = int(np.argmin(np.ptp(along, axis=0) * np.ptp(across, axis=0)))
    return c[k] * u + s[k] * v


def _one_face_axes(a: np.ndarray, q: np.ndarray, prior: ShapeFit) -> np.ndarray:
    """The box's axes (columns, in the prior's order, each its way) when one face is seen:
    its normal ``a`` and the sides of the face's points ``q`` (shape (n, 3)) matched to the
    learnt box's two axes across ``a``, by their lengths where those differ by
    SIDES_DIFFER, else by direction.

    The sides were the learnt axes projected on the face: a box that turned about the
    face's normal since its last fit with two faces kept its old sides, a 9.7 cm side was
    seen 14-16 cm long and refused (random-109-024, observed in 46 % of frames; -007, 48 %,
    in half of every sway)."""
    F, size = prior.frame, prior.size
    assert F is not None and size is not None
    k = int(np.argmax(np.abs(F.T @ a)))
    i, j = [m for m in range(3) if m != k]
    s = _rectangle_side(q, a)
    t = np.cross(a, s)
    if max(size[i], size[j]) > (1 + SIDES_DIFFER) * min(size[i], size[j]):
        b = s if (np.ptp(q @ s) > np.ptp(q @ t)) == (size[i] > size[j]) else t
    else:
        b = s if abs(s @ F[:, i]) >= abs(t @ F[:, i]) else t
    E = np.empty((3, 3))
    E[:, k], E[:, i], E[:, j] = a, b, np.cross(a, b)
    E *= np.sign(np.einsum("ij,ij->j", F, E) + 1e-12)
    if np.linalg.det(E) < 0:
        E[:, j] *= -1
    return E


def _axes(faces: list, prior: ShapeFit | None, p: np.ndarray) -> np.ndarray:
    """The box's axes (columns, right-handed) from its faces' normals, in the prior's order."""
    n = [f[0] for f in faces]
    a = n[0]
    if len(n) > 1:
        b = n[1] - (n[1] @ a) * a
    elif prior is not None and prior.frame is not None and prior.size is not None:
        return _one_face_axes(a, p[faces[0][2]], prior)
    else:  # the seen face's long direction
        q = p[faces[0][2]]
        b = np.linalg.eigh(np.cov((q - q.mean(axis=0)).T))[1][:, -1]
    b /= np.linalg.norm(b)
    E = np.column_stack([a, b, np.cross(a, b)])
    if prior is None or prior.frame is None:
        return E
    order = np.argmax(np.abs(prior.frame.T @ E), axis=1)  # prior axis i ~ E[:, order[i]]
    if len(set(order.tolist())) < 3:
        return E
    E = E[:, order] * np.sign(np.einsum("ij,ij->j", prior.frame, E[:, order]))
    return E if np.linalg.det(E) > 0 else E * np.array([1.0, 1.0, -1.0])


def _edge_gap(q: np.ndarray, direction: np.ndarray) -> float:
    """How far short of a face's edge along ``direction`` its last points fall, metres.

    The points of a face seen obliquely lie in rows; the row spacing along ``direction``
    (the largest step to one of a point's six nearest neighbours) is the step; the last row
    falls half a step short on average. (The density filter before the fit drops more at a
    face seen nearly edge-on: a 4 cm face at 70° still comes out about 8 mm short.)
    """
    _, nn = cKDTree(q).query(q, k=min(7, len(q)))
    step = np.abs((q[nn[:, 1:]] - q[:, None, :]) @ direction).max(axis=1)
    return EDGE_ROWS * float(np.median(step))


def _with_raw(p: np.ndarray, raw: np.ndarray) -> np.ndarray:
    """``p`` (first, in order) and the points of ``raw`` near it (within its extent's
    diagonal of its centroid) that are not in it, the tether's left out
    (:func:`_leaving_lines`). Both shape (n, 3), metres, one frame."""
    centre = p.mean(axis=0)
    reach = float(np.linalg.norm(np.ptp(p, axis=0)))
    near = raw[np.linalg.norm(raw - centre, axis=1) <= reach]
    if not len(near):
        return p
    tree = cKDTree(p)
    d, _ = tree.query(near)
    extra = near[d > 1e-9]
    spacing = float(np.median(tree.query(p, k=2)[0][:, 1])) if len(p) > 1 else 0.0
    return np.vstack([p, extra[~_leaving_lines(p, extra, LINK_SPACINGS * spacing)]])


def _leaving_lines(p: np.ndarray, extra: np.ndarray, link: float) -> np.ndarray:
    """Which points of ``extra`` lie on a line that runs on past the ends of ``p`` along it:
    the tether. Both shape (n, 3), metres; ``link``: the largest step along a line, metres.
    Returns a bool mask, shape (len(extra),).

    Within the object's reach the raw cloud holds 14 cm of a tether below a box; with the
    box's edge it made a plane, taken for a side, and a 7.6 x 6.1 x 24.4 cm box was learnt as
    3.3 x 3.9 x 35.6 cm (observed in 1.7 % of frames, random-109-019). A face seen nearly
    edge-on is a line too, but one that ends where the object does."""
    drop = np.zeros(len(extra), bool)
    if len(extra) < 3 or link <= 0:
        return drop
    pairs = cKDTree(extra).query_pairs(link, output_type="ndarray")
    graph = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])),
                       shape=(len(extra), len(extra)))
    _, labels = connected_components(graph, directed=False)
    for k in np.unique(labels):
        idx = np.flatnonzero(labels == k)
        q = extra[idx]
        if len(q) < 3 or line_width(q) >= LINE_WIDTH_M:
            continue
        u = np.linalg.eigh(np.cov((q - q.mean(axis=0)).T))[1][:, -1]
        along, ends = q @ u, p @ u
        drop[idx] = along.min() < ends.min() - link or along.max() > ends.max() + link
    return drop


def fit_box(points: np.ndarray, viewpoint: np.ndarray, prior: ShapeFit | None = None,
            raw: np.ndarray | None = None) -> ShapeFit:
    """Fit a box to points seen from ``viewpoint``; with ``prior`` (a learnt box), its sizes.

    points : array, shape (n, 3), metres; viewpoint : array, shape (3,), same frame; raw :
    array, shape (m, 3), the points around the object before the density filter, or None.
    With ``raw``, faces and extents come from ``points`` and the raw points near them, and an
    extent is its points' own (no half row added: the edges are all there). Raises
    ValueError if no face is found. The fit's ``frame`` holds the box's axes (columns) and
    ``size`` its extents along them; ``axis`` is its longest axis, ``radius`` half its widest
    extent across that axis (the diagonal), ``length`` its extent along it.
    """
    given, vp = check_points(points), check_vector("viewpoint", viewpoint)
    p = given if raw is None else _with_raw(given, raw)
    faces = _faces(p, vp)
    if not faces:
        raise ValueError("no flat face found")
    faces = _grown(p, faces)
    E = _axes(faces, prior, p)
    normals = np.array([f[0] for f in faces])
    along = np.abs(normals @ E).argmax(axis=1)  # the axis each face is across
    seen_size, centre_e, var, whole = np.zeros(3), np.zeros(3), np.zeros(3), np.zeros(3, bool)
    span = np.zeros(3)  # the points' own extent along each axis, no gaps added
    face_at: dict[int, tuple[float, float, float]] = {}  # axis -> (position, sign, variance)
    rms = np.zeros(len(faces))
    for j, (n, d, idx) in enumerate(faces):
        k = along[j]
        rms[j] = float(np.sqrt(np.mean((p[idx] @ n - d) ** 2)))
        cos = float(n @ E[:, k])
        face_at.setdefault(int(k), (d / cos, float(np.sign(cos)), rms[j] ** 2 / len(idx)))
    for k in range(3):
        side = [f[2] for j, f in enumerate(faces) if along[j] != k]
        if not side:
            continue
        q = p[np.concatenate(side)]
        h = q @ E[:, k]
        lo, hi = np.quantile(h, TRIM), np.quantile(h, 1 - TRIM)
        gap = _edge_gap(q, E[:, k]) if raw is None else 0.0
        whole[k] = True
        if k in face_at:  # from the seen face (exact) to the far edge
            pos, sign, _ = face_at[k]
            span[k] = sign * (pos - (lo if sign > 0 else hi))
            seen_size[k] = span[k] + gap
        else:  # both faces hidden: between the two edges, each short by up to a row (2 gap,
            # uniform): the midpoint's variance is (2 gap)^2 / 12 / 2. Taken as gap^2, a box
            # 1.2 m from a 256-pixel camera was refused as uncertain by 5 mm in 9 frames in
            # 10, its error 2 mm.
            span[k] = hi - lo
            seen_size[k], centre_e[k], var[k] = span[k] + 2 * gap, (lo + hi) / 2, gap**2 / 6
    size = seen_size if prior is None or prior.size is None else prior.size
    longer = whole & (span > size * (1 + LONGER) + MIN_THRESHOLD)
    if longer.any():
        # Its faces were matched to the learnt axes wrongly (a 29 cm side taken for a 4 cm
        # one as the box turned, its centre put 12 cm off with a sigma of 2 mm). The points'
        # own extent, not with the rows' gaps added (2 cm at a face seen at 70 degrees).
        k = int(np.argmax(longer))
        raise ValueError(f"the faces do not fit the learnt box: {span[k] * 100:.1f} cm "
                         f"seen along a {size[k] * 100:.1f} cm side")
    for k in range(3):
        if whole[k] and k not in face_at and seen_size[k] < size[k]:
            # Part of both edges' run is hidden (a dropout, the frame's edge): the centre could
            # lie anywhere along what is missing.
            var[k] += ((size[k] - seen_size[k]) / 2) ** 2
    for k, (pos, sign, v) in face_at.items():
        if prior is None and not whole[k]:
            if len(faces[0][2]) >= FLAT * len(p):
                raise FaceOn("a box seen face-on: its depth is hidden", *faces[0][:2])
            raise ValueError("one face of a box, or no box")
        centre_e[k], var[k] = pos - sign * size[k] / 2, v
    centre = E @ centre_e
    inliers = np.zeros(len(p), bool)
    inliers[np.concatenate([f[2] for f in faces])] = True
    inliers = inliers[:len(given)]
    long = int(np.argmax(size))
    axis = E[:, long] if E[2, long] >= 0 else -E[:, long]
    across = np.delete(size, long)
    cov = E @ np.diag(var) @ E.T
    return ShapeFit("box", centre, axis, float(np.hypot(*across)) / 2, float(size[long]),
                    float(np.sqrt(np.mean(rms**2))), inliers, float(np.sqrt(var.sum())), cov,
                    frame=E, size=np.asarray(size, dtype=float), whole=whole)

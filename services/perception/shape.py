"""Which shape the object is: the sphere, cylinder, box and solid-of-revolution fits compared
while the shape is learnt, and the learnt one used after."""

from __future__ import annotations

import numpy as np

from wavegrasp.perception.box import FaceOn, fit_box
from wavegrasp.perception.fit import ShapeFit, fit_cylinder, fit_sphere, wider_than_seen
from wavegrasp.perception.revolution import SLICE_M, fit_revolution

BOX_EXPLAINED = 0.8  # fit_shape: a box's faces must hold this fraction of the points
EXPLAINED_MORE = 0.05  # fit_shape: or a free outline explains this many more of the points
SHAPE_RMS_RATIO = 0.7  # fit_shape: the cylinder must beat the sphere's RMS by this factor


def fit_shape(points: np.ndarray, viewpoint: np.ndarray, prior: ShapeFit | None = None,
              raw: np.ndarray | None = None) -> ShapeFit:
    """Fit the object: with `prior`, its shape with its sizes fixed; else choose. `raw`: the
    points around the object before the density filter, which a box is learnt from too.

    A box (box.py) wins when its faces hold BOX_EXPLAINED of the points, every extent is seen
    and its RMS is lower; a free solid of revolution (revolution.py: ellipsoids, bottles with
    a neck) when its RMS beats the best so far by SHAPE_RMS_RATIO or it explains
    EXPLAINED_MORE more of the points than a sphere or cylinder (which leave a neck out as
    outliers).

    One flat face holding nearly all the points (box.FaceOn) is a box seen face-on only if
    no curved surface fits by SHAPE_RMS_RATIO better than its plane: at 1.1 m a 4 cm bottle's
    near side lies within the depth noise of one plane, and taken for a face it was refused
    in 443 frames of 450 (the plane 4.5 mm off the points, its cylinder 2.9 and its outline
    1.4 mm; a box's face-on plane and its cylinder of 12 m radius are both 1.4 mm off).

    Else both are fitted with free sizes and the sphere wins unless the cylinder's RMS is below
    SHAPE_RMS_RATIO times the sphere's: a sphere fitted to a cylinder leaves residuals of several
    millimetres (the wall is straight along the axis), a cylinder fitted to a sphere does no
    better than the sphere (measured: 4-7 times worse); ties go to the simpler sphere. A
    sphere, cylinder or outline wider than the points spread across it is none of these
    (:func:`~wavegrasp.perception.fit.wider_than_seen`).
    """
    if prior is not None:
        if prior.shape == "sphere":
            return fit_sphere(points, viewpoint, prior.radius)
        if prior.shape == "box":
            return fit_box(points, viewpoint, prior)
        if prior.shape == "revolution":
            return fit_revolution(points, viewpoint, prior)
        return fit_cylinder(points, viewpoint, prior.radius, prior.length, prior.axis)
    # A sphere or cylinder wider than its points spread across it is no surface that was
    # seen: a face a few pixels wide fits one of any size (fit.wider_than_seen).
    curved = [f for f in (fit_sphere(points, viewpoint), fit_cylinder(points, viewpoint))
              if not seen_narrower(points, viewpoint, f)]
    best = min(curved, default=None,  # the cylinder only below SHAPE_RMS_RATIO of the sphere
               key=lambda f: f.rms * (SHAPE_RMS_RATIO if f.shape == "sphere" else 1.0))
    face_on: FaceOn | None = None
    for fit in (lambda p, v: fit_box(p, v, raw=raw), fit_revolution):
        try:
            other = fit(points, viewpoint)
        except FaceOn as exc:
            face_on = exc
            continue
        except ValueError:
            continue
        if other.shape == "box" and (other.inliers.mean() < BOX_EXPLAINED or not all(
                other.whole) or (best is not None and other.rms >= best.rms)):
            continue
        if best is None:  # no sphere or cylinder was seen: nothing to compare with
            best = other
            continue
        # Explaining more points is a reason only against a sphere or cylinder (which leave a
        # neck out as outliers): a box counts only the points within MIN_THRESHOLD of its
        # faces, so its share is not comparable, and a box whose faces leave a third of a free
        # outline's RMS is the box (a 6 x 29 x 4 cm box was learnt as an outline, 73 mm off).
        explains_more = best.shape != "box" and (
            other.inliers.mean() >= best.inliers.mean() + EXPLAINED_MORE)
        if other.shape == "revolution" and other.rms >= SHAPE_RMS_RATIO * best.rms and (
                not explains_more) and not outline_explains_better(other, best):
            continue
        best = other
    if face_on is not None and (best is None
                                or best.rms >= SHAPE_RMS_RATIO * face_on.rms(points)):
        raise face_on
    if best is None:
        raise ValueError("no shape fits as seen: every curved one is wider than its points")
    return best


def seen_narrower(points: np.ndarray, viewpoint: np.ndarray, fit: ShapeFit) -> bool:
    """Whether the points seen are narrower than the sphere or cylinder ``fit`` to them
    (:func:`~wavegrasp.perception.fit.wider_than_seen`)."""
    return wider_than_seen(points[fit.inliers], fit.centre,
                           None if fit.shape == "sphere" else fit.axis, viewpoint,
                           fit.radius) is not None


#: Free parameters of each fit: a sphere's centre and radius; a cylinder's also its axis and
#: length; an outline's axis (a line, four) and a radius per slice.
PARAMETERS = {"sphere": 4, "cylinder": 7, "revolution": 4}


def outline_explains_better(outline: ShapeFit, other: ShapeFit) -> bool:
    """Does the free outline explain the points better than a sphere or cylinder once its
    many more parameters (a radius per slice) are paid for? The Bayesian information
    criterion over the points both keep: n ln(RSS/n) + k ln n. Near the sensor's noise both
    RMS are close (a 13 x 15 cm ellipsoid: 1.3 against 1.65 mm, over 1000 points), yet
    the sphere's systematic share is as large as the noise, and its radius 6 mm too large."""
    if other.shape not in ("sphere", "cylinder") or min(outline.rms, other.rms) <= 0:
        return False
    n = int(min(outline.inliers.sum(), other.inliers.sum()))
    k_outline = PARAMETERS["revolution"] + outline.length / SLICE_M
    gain = 2.0 * n * np.log(other.rms / outline.rms)
    return bool(gain > (k_outline - PARAMETERS[other.shape]) * np.log(max(n, 2)))

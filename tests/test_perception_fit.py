"""Sphere and cylinder fits on synthetic one-sided clouds: accuracy, honest sigma, shape choice.

A cloud is built the way a stereo camera sees the object: points on the true surface, kept only if
they face the viewpoint (for a convex body that is also the self-occlusion test), with probability
cos(incidence) so the density is uniform in the image; then 1.5 mm (at 1 m) Gaussian noise along
the viewing ray, ~20 points of a 2 mm tether hanging from the object's bottom, and a few strays.
"""

from __future__ import annotations

import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from wavegrasp.perception.box import FaceOn, fit_box
from wavegrasp.perception.fit import (
    ShapeFit,
    check_points,
    fit_cylinder,
    fit_sphere,
    wider_than_seen,
)
from wavegrasp.perception.pipeline import PerceptionConfig, learnt_shape
from wavegrasp.perception.revolution import end_faces, fit_revolution, normals
from wavegrasp.perception.shape import fit_shape

NOISE = 0.0015  # metres, depth noise at 1 m, along the ray
N_POSES = 50
CYLINDERS = [(0.033, 0.122), (0.032, 0.16)]  # radius, length, metres


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def _view(rng: np.random.Generator, centre: np.ndarray) -> np.ndarray:
    """Return a viewpoint ~1 m from `centre`, 10-30 degrees above it, any azimuth."""
    el, az = np.radians(rng.uniform(10, 30)), rng.uniform(0, 2 * np.pi)
    d = rng.uniform(0.9, 1.1)
    return centre + d * np.array([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)])


def _camera(rng, surface, normals, viewpoint, bottom, n_tether=20, n_stray=3):
    """Keep the points a camera at `viewpoint` sees; add noise, a tether from `bottom`, strays."""
    to_cam = viewpoint - surface
    cos = np.einsum("ij,ij->i", normals, _unit(to_cam))
    seen = surface[rng.uniform(size=len(cos)) < cos]  # facing (cos > 0), image-uniform density
    down = _unit(np.array([*rng.normal(0, 0.3, 2), -1.0]))
    s = rng.uniform(0.002, 0.25, n_tether)
    side = _unit(np.cross(down, np.cross(viewpoint - bottom, down)))  # tether's side facing us
    tether = bottom + s[:, None] * down + 0.002 * side
    stray = bottom + rng.uniform(-0.15, 0.15, (n_stray, 3))
    pts = np.vstack([seen, tether, stray])
    ray = pts - viewpoint
    dist = np.linalg.norm(ray, axis=1, keepdims=True)
    return pts + rng.normal(0, NOISE, (len(pts), 1)) * dist**2 * ray / dist


def sphere_cloud(rng, radius=0.06, n=500):
    """Return (points, viewpoint, centre) for a sphere seen from one side."""
    centre = rng.uniform(-0.3, 0.3, 3) + [0, 0, 0.5]
    normals = _unit(rng.normal(size=(4 * n, 3)))
    vp = _view(rng, centre)
    return _camera(rng, centre + radius * normals, normals, vp, centre - [0, 0, radius]), vp, centre


def cylinder_cloud(rng, radius, length, n=500, max_tilt=20.0):
    """Return (points, viewpoint, centre, axis) for a tilted cylinder seen from one side."""
    centre = rng.uniform(-0.3, 0.3, 3) + [0, 0, 0.5]
    tilt, az = np.radians(rng.uniform(0, max_tilt)), rng.uniform(0, 2 * np.pi)
    a = np.array([np.sin(tilt) * np.cos(az), np.sin(tilt) * np.sin(az), np.cos(tilt)])
    e1 = _unit(np.cross(a, [1.0, 0, 0]))
    e2 = np.cross(a, e1)
    vp = _view(rng, centre)
    v = _unit(vp - centre)
    side = 2 * radius * length * np.sqrt(1 - (v @ a) ** 2) + np.pi * radius**2 * abs(v @ a)
    area_wall, area_cap = 2 * np.pi * radius * length, np.pi * radius**2
    total = int(n * (area_wall + 2 * area_cap) / side)
    k_wall = int(total * area_wall / (area_wall + 2 * area_cap))
    k_cap = (total - k_wall) // 2
    th = rng.uniform(0, 2 * np.pi, k_wall)
    radial = np.cos(th)[:, None] * e1 + np.sin(th)[:, None] * e2
    wall = centre + radius * radial + rng.uniform(-length / 2, length / 2, (k_wall, 1)) * a
    caps, cap_normals = [], []
    for sign in (1, -1):
        rr, ph = radius * np.sqrt(rng.uniform(size=k_cap)), rng.uniform(0, 2 * np.pi, k_cap)
        disc = rr[:, None] * (np.cos(ph)[:, None] * e1 + np.sin(ph)[:, None] * e2)
        caps.append(centre + sign * length / 2 * a + disc)
        cap_normals.append(np.tile(sign * a, (k_cap, 1)))
    surface = np.vstack([wall, *caps])
    normals = np.vstack([radial, *cap_normals])
    return _camera(rng, surface, normals, vp, centre - length / 2 * a), vp, centre, a


def _stats(errors: np.ndarray, sigmas: np.ndarray) -> tuple[float, float, float]:
    """Return RMSE (metres), |mean error| (metres), fraction with |error| < 2 sigma."""
    norms = np.linalg.norm(errors, axis=1)
    rmse = float(np.sqrt(np.mean(norms**2)))
    return rmse, float(np.linalg.norm(errors.mean(axis=0))), float(np.mean(norms < 2 * sigmas))


@pytest.mark.parametrize("fixed,n", [(False, 500), (True, 500), (False, 150)])
def test_sphere_centre_is_unbiased_and_sigma_honest(fixed: bool, n: int) -> None:
    """n = 150: the tether is an eighth of the points, enough to pull a soft-L1 fit away."""
    rng = np.random.default_rng(1)
    errors, sigmas, naive = [], [], []
    for _ in range(N_POSES):
        pts, vp, centre = sphere_cloud(rng, n=n)
        fit = fit_sphere(pts, vp, radius=0.06 if fixed else None)
        assert fit.shape == "sphere" and fit.inliers.shape == (len(pts),)
        errors.append(fit.centre - centre)
        sigmas.append(fit.sigma)
        naive.append(np.linalg.norm(pts.mean(axis=0) - centre))
    rmse, bias, within = _stats(np.array(errors), np.array(sigmas))
    assert rmse < 0.002 and bias < 0.001
    assert within >= 0.85
    assert np.median(naive) > 10 * rmse  # the visible-surface centroid is far off


@pytest.mark.parametrize("radius,length", CYLINDERS)
@pytest.mark.parametrize("known", [True, False])
def test_cylinder_centre_is_unbiased_and_sigma_honest(radius, length, known) -> None:
    rng = np.random.default_rng(2)
    errors, sigmas, naive = [], [], []
    for _ in range(N_POSES):
        pts, vp, centre, axis = cylinder_cloud(rng, radius, length)
        fit = (fit_cylinder(pts, vp, radius, length) if known else fit_cylinder(pts, vp))
        assert fit.shape == "cylinder" and abs(np.linalg.norm(fit.axis) - 1) < 1e-9
        assert np.degrees(np.arccos(abs(fit.axis @ axis))) < 3
        errors.append(fit.centre - centre)
        sigmas.append(fit.sigma)
        naive.append(np.linalg.norm(pts.mean(axis=0) - centre))
    rmse, bias, within = _stats(np.array(errors), np.array(sigmas))
    assert rmse < (0.002 if known else 0.004) and bias < 0.001
    assert within >= 0.85
    assert np.median(naive) > 5 * rmse


def test_fit_shape_picks_the_shape_and_uses_the_prior() -> None:
    rng = np.random.default_rng(3)
    right, total = 0, 0
    for i in range(N_POSES):
        pts, vp, _ = sphere_cloud(rng)
        right += fit_shape(pts, vp).shape == "sphere"
        radius, length = CYLINDERS[i % 2]
        pts, vp, centre, _ = cylinder_cloud(rng, radius, length)
        right += fit_shape(pts, vp).shape == "cylinder"
        total += 2
    assert right / total >= 0.95
    prior = ShapeFit("cylinder", centre, np.array([0.0, 0.0, 1.0]), radius, length, 0.0,
                     np.ones(1, bool), 0.0)  # cov is optional: a learnt prior has none
    fit = fit_shape(pts, vp, prior)
    assert fit.shape == "cylinder" and fit.radius == radius and fit.length == length
    assert np.linalg.norm(fit.centre - centre) < 0.005


def ellipsoid_cloud(rng, radius, half_length, n=500):
    """Return (points, viewpoint, centre) for an upright ellipsoid of revolution seen from one
    side: equator ``radius``, poles ``half_length`` from its centre."""
    centre = rng.uniform(-0.3, 0.3, 3) + [0, 0, 0.5]
    u = _unit(rng.normal(size=(4 * n, 3)))
    axes = np.array([radius, radius, half_length])
    vp = _view(rng, centre)
    return _camera(rng, centre + u * axes, _unit(u / axes), vp,
                   centre - [0, 0, half_length]), vp, centre


@pytest.mark.parametrize("radius, half_length", [(0.065, 0.073), (0.06, 0.04)])
def test_a_near_sphere_or_flat_ellipsoid_is_fitted_by_its_outline(radius, half_length) -> None:
    """A 13 x 15 cm ellipsoid was learnt as a sphere 14.4 cm across (wider than a 14 cm jaw
    opens): the outline's RMS was within 30 % of the sphere's, both near the noise. A flat
    one was fitted about a wrong axis. Both are now their outline, about their own axis."""
    rng = np.random.default_rng(5)
    fits = [fit_shape(*ellipsoid_cloud(rng, radius, half_length)[:2]) for _ in range(20)]
    assert sum(f.shape == "revolution" for f in fits) >= 16, [f.shape for f in fits]
    outlines = [f for f in fits if f.shape == "revolution"]
    assert np.median([abs(f.axis[2]) for f in outlines]) > 0.95
    assert np.median([f.radius for f in outlines]) == pytest.approx(radius, abs=0.004)


def test_a_view_as_near_its_points_as_a_fine_clouds_learnt_outline_is_not_refused(
        monkeypatch: pytest.MonkeyPatch) -> None:
    """A noise-free cloud's learnt outline is 0.14-0.2 mm off its points and another view's
    0.2-0.5 mm: 1.5 times the learnt RMS refused a quarter of a 31 cm bottle's frames as
    partial views. Within a millimetre a fit is no partial view's."""
    monkeypatch.setattr(sys.modules[__name__], "NOISE", 0.0)
    rng = np.random.default_rng(3)
    for radius, half_length in [(0.05, 0.155), (0.05, 0.09), (0.04, 0.12)]:
        fits = [fit_revolution(*ellipsoid_cloud(rng, radius, half_length)[:2])
                for _ in range(9)]
        learnt = sorted(fits, key=lambda f: f.rms)[4]
        assert learnt.rms < 0.0005
        for _ in range(30):
            points, viewpoint, centre = ellipsoid_cloud(rng, radius, half_length)
            try:
                fit = fit_revolution(points, viewpoint, learnt)
            except ValueError as exc:
                assert "off the points" not in str(exc)
                continue
            assert np.linalg.norm(fit.centre - centre) < 0.004


def test_a_solid_of_revolution_seen_longer_than_it_was_learnt_is_not_refused() -> None:
    """random-127-001: an ellipsoid 10.4 cm across and 9.2 cm along its axis was seen 7.6 cm
    long in every learning frame, then 8.4-8.8 cm as it swung; those views were refused as
    partial ones (the outline longer than the learnt one from its end face), and the object
    was observed in 9 % of frames. A view longer than the learning's sees more of it."""
    rng = np.random.default_rng(7)
    radius, half_length = 0.052, 0.046

    def lower_end_hidden():
        points, viewpoint, centre = ellipsoid_cloud(rng, radius, half_length)
        return points[points[:, 2] > centre[2] - 0.4 * half_length], viewpoint

    learnt = learnt_shape([fit_revolution(*lower_end_hidden()) for _ in range(9)])
    assert learnt.length < 2 * half_length - 0.015  # learnt short, as in the recording
    for _ in range(10):
        points, viewpoint, centre = ellipsoid_cloud(rng, radius, half_length)
        fit = fit_revolution(points, viewpoint, learnt)  # raised "(a partial view)"
        assert fit.length > learnt.length
        assert np.linalg.norm(fit.centre - centre) < 0.004, fit.centre - centre


def test_a_view_of_part_of_an_outline_is_placed_where_it_fits_the_learnt_one() -> None:
    """random-199-007: an 8 x 9 cm ellipsoid seen from above showed less than its learnt
    length in half its frames, none with a flat end, and each was refused as a partial view
    (304 of 600 frames). Where the seen part of the outline fits the learnt one places it."""
    rng = np.random.default_rng(11)
    radius, half_length = 0.04, 0.05
    learnt = learnt_shape([fit_revolution(*ellipsoid_cloud(rng, radius, half_length)[:2])
                           for _ in range(9)])
    errors = []
    for _ in range(10):
        points, viewpoint, centre = ellipsoid_cloud(rng, radius, half_length)
        part = points[points[:, 2] > centre[2] - 0.2 * half_length]
        fit = fit_revolution(part, viewpoint, learnt)  # raised "(a partial view)"
        errors.append(fit.centre - centre)
        assert fit.sigma < 0.005
    assert np.sqrt(np.mean(np.sum(np.square(errors), axis=1))) < 0.003


def test_a_straight_wall_seen_without_its_ends_is_too_uncertain_to_place() -> None:
    """A cylinder's wall fits its learnt outline anywhere along the straight body: the
    centre such a view gives is too uncertain for perception to report (its sigma above
    ``max_sigma_m``), not placed at whichever shift the noise favours."""
    rng = np.random.default_rng(12)
    radius, length = 0.04, 0.24

    def view():
        points, viewpoint, centre, axis = cylinder_cloud(rng, radius, length, max_tilt=0.0)
        return points, viewpoint, centre

    learnt = learnt_shape([fit_revolution(*view()[:2]) for _ in range(9)])
    for _ in range(5):
        points, viewpoint, centre = view()
        middle = points[np.abs(points[:, 2] - centre[2]) < 0.25 * length]
        fit = fit_revolution(middle, viewpoint, learnt)
        assert fit.sigma > PerceptionConfig().max_sigma_m, np.linalg.norm(fit.centre - centre)


def test_a_solid_of_revolution_that_turned_far_between_frames_is_fitted_from_its_points() -> None:
    """random-199-028: a 28 cm bottle in a 33 cm sea seen at 5 Hz turned 41 degrees between
    frames; fitted from the last frame's axis, the outline ended 6 mm off the points and the
    frame was refused, as were half of the recording's. From the points' own longest
    direction it is placed as well as any."""
    z = np.load(Path(__file__).parent / "data" / "bottle-turned-between-frames.npz")
    prior = ShapeFit("revolution", z["prior_centre"], z["prior_axis"], float(z["radius"]),
                     float(z["length"]), float(z["rms"]), np.ones(1, bool), 0.001,
                     offset=float(z["offset"]), outline=z["outline"])
    assert np.degrees(np.arccos(prior.axis @ z["true_axis"])) > 40
    fit = fit_revolution(z["points"].astype(float), z["eye"], prior)
    assert np.linalg.norm(fit.centre - z["centre"]) < 0.002
    assert np.degrees(np.arccos(abs(fit.axis @ z["true_axis"]))) < 3


def test_check_points_names_the_problem() -> None:
    good = np.zeros((30, 3))
    assert check_points(good).shape == (30, 3)
    with pytest.raises(ValueError, match="shape"):
        check_points(np.zeros((30, 2)))
    with pytest.raises(ValueError, match="NaN"):
        check_points(np.vstack([good, [[np.nan, 0, 0]]]))
    with pytest.raises(ValueError, match="at least 20"):
        check_points(np.zeros((5, 3)))
    with pytest.raises(ValueError, match="viewpoint"):
        fit_sphere(good, [0.0, 0.0])
    with pytest.raises(ValueError, match="radius"):
        fit_cylinder(good, np.zeros(3), radius=-1.0)


def box_faces(rng, size, turn_deg, centre, eye, spacing=0.006):
    """Points on the faces of a box (``size`` along its axes, metres, turned about z) that a
    camera at ``eye`` sees, image-uniform with ``spacing`` at head-on incidence; no noise.
    Returns (points, normals), each shape (n, 3)."""
    turn = np.radians(turn_deg)
    R = np.array([[np.cos(turn), -np.sin(turn), 0.0], [np.sin(turn), np.cos(turn), 0.0],
                  [0.0, 0.0, 1.0]])
    points, normals = [], []
    for k in range(3):
        for sign in (-1.0, 1.0):
            n = sign * R[:, k]
            on = centre + n * size[k] / 2
            if n @ (eye - on) <= 0:
                continue
            a, b = [j for j in range(3) if j != k]
            m = int(size[a] * size[b] / spacing**2 * (n @ (eye - on)) / np.linalg.norm(eye - on))
            u = rng.uniform(-0.5, 0.5, (m, 2))
            points.append(on + u[:, :1] * size[a] * R[:, a] + u[:, 1:] * size[b] * R[:, b])
            normals.append(np.tile(n, (m, 1)))
    return np.vstack(points), np.vstack(normals)


def test_a_box_whose_faces_fit_is_not_taken_for_a_free_outline() -> None:
    """A thin box (6.4 x 4 x 29 cm) seen on two faces, with the noise tails a stereo camera
    gives: a free outline keeps more of the points as inliers than the faces' tight
    threshold does, but leaves four times the RMS; the box is the shape (in the random
    suite such a box was learnt as an outline, its centroid 73 mm off)."""
    rng = np.random.default_rng(0)
    centre, eye = np.array([0.0, 0.0, 0.35]), np.array([0.86, 1.05, 0.92])
    points, normals = box_faces(rng, np.array([0.064, 0.04, 0.29]), 10.0, centre, eye)
    m = len(points)
    tail = rng.random(m) < 0.3
    noise = np.where(tail, rng.normal(0, 0.003, m), rng.normal(0, 0.0007, m))
    fit = fit_shape(points + noise[:, None] * normals, eye)
    assert fit.shape == "box"
    assert np.linalg.norm(fit.centre - centre) < 0.005


def thin_box_far(seed: int) -> tuple[np.ndarray, np.ndarray]:
    """A 4.2 x 2.8 x 30 cm box turned 59 degrees, 1.6 m from a camera 15-25 degrees above
    it with 7.6 mm pixels there (256 px across 70 degrees) and its depth noise (3.8 mm):
    each face a few pixels wide (random-151-020). Returns (points, eye)."""
    rng = np.random.default_rng(seed)
    centre = np.array([0.0, 0.0, 0.46])
    el, az = np.radians(rng.uniform(15, 25)), rng.uniform(0, 2 * np.pi)
    eye = centre + 1.6 * np.array([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az),
                                   np.sin(el)])
    points, _ = box_faces(rng, np.array([0.042, 0.028, 0.30]), 59.0, centre, eye,
                          spacing=0.0076)
    ray = points - eye
    dist = np.linalg.norm(ray, axis=1, keepdims=True)
    return points + rng.normal(0, NOISE, (len(points), 1)) * dist * ray, eye


def test_a_curved_surface_wider_than_its_points_is_no_surface_seen() -> None:
    """A face a few pixels wide lies on an arc of any large circle: outlines of 4-25 cm
    radius and spheres of tens of metres were fitted to a thin box's faces, and it was
    learnt as a solid 14.8 cm across (random-151-020). A sphere, cylinder or outline wider
    than the points spread across it is refused; the surfaces that were seen are not."""
    rng = np.random.default_rng(2)
    for _ in range(10):
        points, vp, centre = sphere_cloud(rng, radius=0.05)
        seen = points[fit_sphere(points, vp).inliers]  # not the tether's nor strays
        assert wider_than_seen(seen, centre, None, vp, 0.05) is None
        assert wider_than_seen(seen, centre, None, vp, 0.1) is not None
        points, vp, centre, axis = cylinder_cloud(rng, 0.03, 0.2)
        seen = points[fit_cylinder(points, vp).inliers]
        assert wider_than_seen(seen, centre, axis, vp, 0.03) is None
        assert wider_than_seen(seen, centre, axis, vp, 0.07) is not None
    for seed in range(12):
        points, eye = thin_box_far(seed)
        centre = points.mean(axis=0)
        reason = wider_than_seen(points, centre, np.array([0.0, 0.0, 1.0]), eye, 0.074)
        assert reason is not None and "flat face" in reason
        try:
            fit = fit_shape(points, eye)
        except ValueError:
            continue
        assert fit.shape == "box" or fit.radius < 0.035, (seed, fit.shape, fit.radius)


@pytest.mark.parametrize("seed", range(10))
def test_a_box_seen_from_far_and_nearly_level_is_a_box_near_its_centre(seed: int) -> None:
    """A 9 x 8 x 28 cm box 1.2-1.45 m from a camera 3-15 degrees above it, any turn within 30
    degrees of face-on: the depth noise there (2-3 mm) is as wide as the faces' RANSAC
    threshold, and the top face is seen at a grazing angle. Its faces must still explain the
    cloud (before, a sphere or outline was fitted to half such views, and a box seen so was
    never observed), or the view is named face-on; the centre is off only by the rows a
    grazing face's far edge falls short (a fitted normal turned inside out put it 5 cm off)."""
    rng = np.random.default_rng(seed)
    size, centre = np.array([0.088, 0.081, 0.28]), np.array([0.0, 0.0, 0.4])
    el, d = np.radians(rng.uniform(3, 15)), rng.uniform(1.2, 1.45)
    eye = centre + d * np.array([-np.cos(el), 0.0, np.sin(el)])
    points, _ = box_faces(rng, size, rng.uniform(-30, 30), centre, eye, spacing=0.0065)
    ray = points - eye
    dist = np.linalg.norm(ray, axis=1, keepdims=True)
    points = points + rng.normal(0, NOISE, (len(points), 1)) * dist * ray
    try:
        fit = fit_shape(points, eye)
    except FaceOn:
        return
    assert fit.shape == "box"
    assert np.linalg.norm(fit.centre - centre) < 0.01


def test_a_box_whose_faces_match_the_learnt_axes_wrongly_is_refused_not_reported_off() -> None:
    """A 6.4 x 4 x 29 cm box whose learnt axes are matched to its faces wrongly (as a turning
    box's were: its long side taken for its thin one, random-7-002): its centre came out
    12 cm off with a sigma of 2 mm. A side seen half as long again as learnt is refused,
    naming it."""
    size, centre = np.array([0.064, 0.04, 0.29]), np.array([0.0, 0.0, 0.4])
    eye = centre + np.array([-0.8, -0.5, 0.35])
    for seed in range(5):
        rng = np.random.default_rng(seed)
        p0, n0 = box_faces(rng, size, 10.0, centre, eye, spacing=0.004)
        prior = fit_box(p0 + rng.normal(0, 0.0007, (len(p0), 1)) * n0, eye)
        assert prior.frame is not None and prior.size is not None
        long, thin = int(np.argmax(prior.size)), int(np.argmin(prior.size))
        order = np.arange(3)
        order[[long, thin]] = order[[thin, long]]
        swapped = replace(prior, frame=prior.frame[:, order] * [1.0, 1.0, -1.0])
        p1, n1 = box_faces(rng, size, 10.0, centre, eye, spacing=0.004)
        with pytest.raises(ValueError, match="learnt box"):
            fit_box(p1 + rng.normal(0, 0.0007, (len(p1), 1)) * n1, eye, swapped)


@pytest.mark.parametrize("roll_deg", [20.0, 35.0, 60.0, -75.0])
def test_a_box_seen_on_one_face_is_placed_however_it_turned_about_that_face(
        roll_deg: float) -> None:
    """An 11.5 x 19.9 x 9.7 cm box learnt from a view of three faces, then seen face-on
    after it turned about that face's normal. Its sides were the learnt axes projected on the
    face: a 9.7 cm side turned 20 degrees is seen 15.9 cm long, and the frame was refused
    (random-109-024: observed in 46 % of frames). The sides now come from the face's
    outline, matched to the learnt sizes."""
    rng = np.random.default_rng(1)
    size, centre = np.array([0.115, 0.199, 0.097]), np.array([0.0, 0.0, 0.4])
    oblique = centre + np.array([-0.7, -0.5, 0.5])
    p0, n0 = box_faces(rng, size, 0.0, centre, oblique, spacing=0.004)
    prior = fit_box(p0 + rng.normal(0, 0.0007, (len(p0), 1)) * n0, oblique)
    eye = centre + np.array([-1.0, 0.0, 0.0])
    p1, n1 = box_faces(rng, size, 0.0, centre, eye, spacing=0.004)
    roll = np.radians(roll_deg)
    R = np.array([[1.0, 0.0, 0.0], [0.0, np.cos(roll), -np.sin(roll)],
                  [0.0, np.sin(roll), np.cos(roll)]])
    p1 = (p1 - centre) @ R.T + centre + rng.normal(0, 0.0007, (len(p1), 1)) * n1
    fit = fit_box(p1, eye, prior)
    assert np.linalg.norm(fit.centre - centre) < 0.003
    assert fit.frame is not None and prior.frame is not None
    turned = R @ prior.frame  # the learnt axes, turned with the box
    assert np.all(np.abs(np.einsum("ij,ij->j", fit.frame, turned)) > np.cos(np.radians(3)))


def test_a_flat_end_is_told_from_a_curved_cap() -> None:
    """A revolution's end is a face only if it is flat: a 10 cm cylinder's top (its normals
    along the axis, within the sensor's noise of one plane) is, a sphere's or a flat
    ellipsoid's cap (its normals as near the axis, but bulging 3-8 mm) is not."""
    rng = np.random.default_rng(0)
    axis, centre = np.array([0.0, 0.0, 1.0]), np.zeros(3)
    th, r = rng.uniform(0, 2 * np.pi, 1500), 0.05 * np.sqrt(rng.uniform(size=1500))
    top = np.column_stack([r * np.cos(th), r * np.sin(th), np.full(1500, 0.06)])
    wall = np.column_stack([0.05 * np.cos(th), 0.05 * np.sin(th), rng.uniform(-0.06, 0.06,
                                                                               1500)])
    cylinder = np.vstack([top, wall]) + rng.normal(0, 0.0005, (3000, 3))
    end = end_faces(cylinder, normals(cylinder), centre, axis)
    assert (end[:1500] == 1).mean() > 0.8 and (end[1500:] == 0).mean() > 0.95
    for half_axes in ([0.035, 0.035, 0.035], [0.06, 0.06, 0.04]):
        u = _unit(rng.normal(size=(3000, 3)))
        cap = u[u[:, 2] > 0] * half_axes + rng.normal(0, 0.0005, ((u[:, 2] > 0).sum(), 3))
        assert not end_faces(cap, normals(cap), centre, axis).any()


def test_a_bottle_seen_base_up_is_a_solid_of_revolution_not_a_box() -> None:
    """The first frame of random-101-011 (``wavegrasp eval --suite random --seed 101``): a
    bottle 9.1 cm across and 15.5 cm long hanging neck down, the camera 33 degrees above it.
    ``tests/data/bottle-base-up-frame.npz`` holds the points perception fitted (world,
    metres) and the camera's position. Its base faces the camera and holds most of them:
    counted as wall, no axis through them fitted ("the outline's centre falls outside the
    object"), and a box 1 mm off its faces was taken, and learnt (its centroid 15 mm high,
    56 % of frames observed). Each start axis's end faces are now tried too."""
    frame = np.load(Path(__file__).parent / "data" / "bottle-base-up-frame.npz")
    fit = fit_shape(frame["points"].astype(float), frame["viewpoint"])
    assert fit.shape == "revolution"
    assert fit.radius == pytest.approx(0.0454, abs=0.003)


def test_the_tether_in_the_raw_cloud_is_no_side_of_a_box() -> None:
    """A learning frame of random-109-019 (``wavegrasp eval --suite random --seed 109``): a
    7.6 x 6.1 x 24.4 cm box nearly face-on, 1.02 m from the camera.
    ``tests/data/box-tether-frame.npz`` holds the points perception fitted, the raw points
    around them (before the density filter: the sides seen at a grazing angle, sparse, and
    14 cm of the tether below the box) and the camera's position, world, metres. The tether's
    line and the box's edge made a plane, taken for a side: a 3.2 x 3.8 x 35.3 cm box, and a
    box learnt so was observed in 1.7 % of frames. The front face holds nearly all the
    points: the view is face-on."""
    frame = np.load(Path(__file__).parent / "data" / "box-tether-frame.npz")
    with pytest.raises(FaceOn):
        fit_box(frame["points"].astype(float), frame["viewpoint"],
                raw=frame["raw"].astype(float))


def _upright_cylinder(rng: np.random.Generator, radius: float, length: float,
                      centre: np.ndarray, n: int = 8000) -> tuple[np.ndarray, np.ndarray]:
    """Points and outward normals, shapes (m, 3), of a closed upright cylinder's surface."""
    th, ph = rng.uniform(0, 2 * np.pi, n), rng.uniform(0, 2 * np.pi, n // 4)
    radial = np.column_stack([np.cos(th), np.sin(th), np.zeros(n)])
    wall = centre + radius * radial + np.outer(rng.uniform(-length / 2, length / 2, n),
                                               [0.0, 0.0, 1.0])
    rr = radius * np.sqrt(rng.uniform(size=n // 4))
    disc = np.column_stack([rr * np.cos(ph), rr * np.sin(ph), np.zeros(n // 4)])
    up = np.tile([0.0, 0.0, 1.0], (n // 4, 1))
    return (np.vstack([wall, centre + disc + up * length / 2, centre + disc - up * length / 2]),
            np.vstack([radial, up, -up]))


def test_a_solid_of_revolution_seen_end_on_is_placed_from_its_end_face() -> None:
    """random-101-011: a bottle 9 cm across and 15.5 cm long hangs neck down below a camera
    33 degrees above it; in many frames it shows its base and the top of its body only. No
    axis through the points fitted while the base was counted as wall (the outline's centre
    fell outside the object), a box was learnt, and its centroid was 15 mm high in 56 % of
    frames. The base's face is now an end from the first axis tried; and with the length
    learnt from the views that saw the whole, a view that sees less is placed from the one
    flat end it sees, where before it was refused as a partial view."""
    rng = np.random.default_rng(11)
    radius, length, centre = 0.045, 0.155, np.array([0.1, -0.2, 0.5])
    surface, outward = _upright_cylinder(rng, radius, length, centre)

    def view(elevation_deg: float, hidden_below_m: float | None = None):
        el, az = np.radians(elevation_deg), rng.uniform(0, 2 * np.pi)
        vp = centre + 0.6 * np.array([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az),
                                      np.sin(el)])
        points = _camera(rng, surface, outward, vp, centre - [0, 0, length / 2], n_tether=0)
        if hidden_below_m is not None:
            points = points[points[:, 2] > centre[2] + hidden_below_m]
        return points, vp

    learnt = learnt_shape([fit_revolution(*view(15.0)) for _ in range(9)])
    assert learnt.length == pytest.approx(length, abs=0.01)
    for _ in range(10):
        points, vp = view(65.0, hidden_below_m=-0.01)
        alone = fit_revolution(points, vp)  # raised "the outline's centre falls outside"
        assert alone.length < 0.1
        fit = fit_revolution(points, vp, learnt)
        assert np.linalg.norm(fit.centre - centre) < 0.004, fit.centre - centre

"""Objects no sphere or cylinder fits: boxes, ellipsoids, bottles with a neck.

The generator builds them (closed meshes about their volume centroid, tethered at one end) and
perception finds their volume centroid: a box from its faces, the others as a free solid of
revolution. Recordings of the paper's tank (wave 2) with the 30 k-point camera; the sim
holds the recording's own object, and the pipeline grasps each.
"""

from __future__ import annotations

import subprocess
import sys
from collections.abc import Iterator
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from wavegrasp.ops.bench_perception import FAMILIES, family_scenario
from wavegrasp.perception.evaluate import evaluate, run_perception
from wavegrasp.perception.fit import ShapeFit
from wavegrasp.perception.main import observation
from wavegrasp.perception.pipeline import FrameResult, Perception, axial_span
from wavegrasp.planner.collision import Body
from wavegrasp.recording_io.reader import open_recording
from wavegrasp.recording_io.ros_msgs import StaticTransforms, decode_points, decode_tf
from wavegrasp.schemas import Header
from wavegrasp.wavetank.body import profile, solid_of_revolution
from wavegrasp.wavetank.camera import object_mesh
from wavegrasp.wavetank.record import generate
from wavegrasp.wavetank.scenario import ObjectModel, Scenario

from conftest import own_messages, wavegrasp_cmd

BOTTLE = {"family": "bottle", "diameter_m": 0.065, "length_m": 0.2, "neck_diameter_m": 0.027,
          "neck_length_m": 0.04, "mass_kg": 0.12}


def test_a_solid_of_revolution_has_the_volume_and_centroid_of_its_frusta() -> None:
    volume, centroid = solid_of_revolution(np.array([0.0, 1.0]), np.array([1.0, 0.0]))
    assert volume == pytest.approx(np.pi / 3) and centroid == pytest.approx(0.25)  # a cone
    volume, centroid = solid_of_revolution(np.array([0.0, 0.1, 0.3]), np.array([0.01, 0.01,
                                                                                 0.01]))
    assert volume == pytest.approx(np.pi * 1e-4 * 0.3) and centroid == pytest.approx(0.15)


@pytest.mark.parametrize("obj", [
    BOTTLE, {**BOTTLE, "neck": "up"},
    {"family": "box", "diameter_m": 0.08, "depth_m": 0.05, "length_m": 0.15, "mass_kg": 0.2,
     "turn_deg": 30},
    {"family": "ellipsoid", "diameter_m": 0.08, "length_m": 0.15, "mass_kg": 0.2}])
def test_each_mesh_is_closed_with_its_volume_about_its_volume_centroid(obj: dict) -> None:
    spec = ObjectModel(**obj).spec()
    legacy = object_mesh(spec).to_legacy()
    v, t = np.asarray(legacy.vertices), np.asarray(legacy.triangles)
    a, b, c = v[t[:, 0]], v[t[:, 1]], v[t[:, 2]]
    tet = np.einsum("ij,ij->i", a, np.cross(b, c)) / 6
    assert legacy.is_watertight()
    assert tet.sum() == pytest.approx(spec.volume, rel=0.01)
    assert np.abs((tet[:, None] * (a + b + c) / 4).sum(axis=0) / tet.sum()).max() < 1e-4
    # The narrow neck moves the volume centroid away from it, by more than half a centimetre.
    if obj["family"] == "bottle":
        towards_tether = spec.length / 2 - spec.attach_offset
        assert towards_tether < -0.005 if spec.neck_down else towards_tether > 0.005


@pytest.mark.parametrize(("obj", "problem"), [
    ({**BOTTLE, "neck_length_m": 0.19}, "neck_length_m: the neck and its 45° shoulder leave"),
    ({**BOTTLE, "neck_diameter_m": 0.07}, "neck_diameter_m: must be narrower"),
    ({"family": "box", "diameter_m": 0.08, "length_m": 0.15, "mass_kg": 0.2},
     "depth_m: only a box has one"),
    ({"family": "ellipsoid", "diameter_m": 0.08, "mass_kg": 0.2}, "length_m: a ellipsoid needs"),
    ({"family": "cylinder", "diameter_m": 0.08, "length_m": 0.1, "neck_length_m": 0.02,
      "mass_kg": 0.2}, "a bottle needs both"),
])
def test_an_object_that_cannot_be_is_refused_naming_the_field(obj: dict, problem: str) -> None:
    with pytest.raises(ValueError, match=problem):
        ObjectModel(**obj)


#: The families perception's accuracy is tested on (label prefixes of FAMILIES). The flat
#: ellipsoid's outline was fitted about a wrong axis and learnt as a sphere (6.9 mm off, 69 %
#: of frames); the 6 x 4 x 10 cm box's side, seen at 70 degrees, was thinned by the density
#: filter and its depth learnt short (4.3 mm off, 85 % of frames).
ACCURACY = ("box 8 x 5 x 15 cm, turned", "ellipsoid 7", "ellipsoid 12", "bottle 6.5",
            "box 6 x 4 x 10")


@pytest.fixture(scope="module")
def recordings(tmp_path_factory) -> dict[str, Path]:
    out = tmp_path_factory.mktemp("families")
    paths = {}
    for label, wave, obj in FAMILIES:
        if label.startswith(ACCURACY):
            paths[label] = out / f"{len(paths)}.mcap"
            generate(family_scenario(label, wave, obj, 8.0, 1), paths[label])
    return paths


@pytest.mark.parametrize("prefix", ACCURACY)
def test_perception_finds_the_volume_centroid_of_each_family(recordings, prefix: str) -> None:
    path = next(p for label, p in recordings.items() if label.startswith(prefix))
    ev = evaluate(path)
    assert ev.observed >= 0.9, ev.row()
    assert ev.rmse <= 0.003, ev.row()


def perceived(path: Path, perception: Perception) -> Iterator[FrameResult]:
    """``perception``'s result for each camera frame of the recording at ``path``."""
    tf = StaticTransforms()
    for m in open_recording(path).messages():
        if m.topic == "/tf_static":
            tf.update(decode_tf(m.cdr))
        elif m.topic == "/trisect/points":
            cloud = decode_points(m.cdr)
            yield perception.process(cloud.points, tf.lookup("world", cloud.frame_id),
                                     cloud.stamp_ns)


def test_a_box_learnt_from_its_faces_reports_its_shape(recordings) -> None:
    path = next(p for label, p in recordings.items() if label.startswith("box"))
    track = run_perception(path)
    assert np.isfinite(track.centres[:, 0]).mean() >= 0.9
    # A cylinder or sphere fit of the same points is off by more than a centimetre.
    perception = Perception()
    shapes = {result.fit.shape for result in perceived(path, perception) if result.fit}
    assert shapes == {"box"}
    assert perception.prior is not None and perception.prior.size is not None
    assert np.sort(perception.prior.size) == pytest.approx([0.05, 0.08, 0.15], abs=0.006)


def test_a_box_is_perceived_bit_identically_in_every_process(recordings) -> None:
    """Its faces come from open3d's RANSAC, whose samples its threads drew in whatever order
    they came: the same recording gave other centroids in each process, and lockstep runs
    of a box did not repeat."""
    path = next(p for label, p in recordings.items() if label.startswith("box"))
    code = ("import hashlib, sys, numpy as np; from wavegrasp.perception.evaluate import "
            "run_perception; t = run_perception(sys.argv[1]); "
            "print(hashlib.sha1(np.nan_to_num(t.centres).tobytes()).hexdigest())")
    digests = {subprocess.run([sys.executable, "-c", code, str(path)], capture_output=True,
                              text=True, check=True, timeout=120).stdout for _ in range(3)}
    assert len(digests) == 1, digests


def test_the_planner_models_a_bottle_from_its_base_to_its_neck(recordings) -> None:
    """A bottle's centroid lies towards its body, so its ends are not equally far from it:
    the planner's capsule, centred on the centroid, left 3 cm of a 23 cm bottle's neck
    outside. Perception now says where the middle of its length lies."""
    label, path = next((k, v) for k, v in recordings.items() if k.startswith("bottle"))
    spec = ObjectModel(name="bottle", **next(o for lab, _, o in FAMILIES if lab == label)).spec()
    z, r = profile(spec)
    centroid = solid_of_revolution(z, r)[1]
    below, above = centroid, spec.length - centroid  # the neck down: the longer end below
    assert below - above > 0.03
    bodies = [Body.from_observation(observation(Header(), r.fit, len(r.points), r.span))
              for r in perceived(path, Perception()) if r.fit is not None]
    assert len(bodies) > 60
    up = np.array([0.0, 0.0, 1.0])
    tops = [b.extent(np.sign(b.axis[2]) * b.axis) for b in bodies[-40:]]
    bottoms = [b.extent(-np.sign(b.axis[2]) * b.axis) for b in bodies[-40:]]
    assert np.median(bottoms) == pytest.approx(below, abs=0.008)
    assert np.median(tops) == pytest.approx(above, abs=0.008)
    assert bodies[-1].extent(up) < bodies[-1].extent(-up)


def test_an_objects_ends_are_where_its_points_reach_past_its_fitted_shape() -> None:
    """A bottle whose body is fitted as a cylinder: its neck's points are no part of the
    fit but are the object's; a stray point is no end."""
    rng = np.random.default_rng(1)
    body = np.column_stack([0.04 * np.cos(t := rng.uniform(0, np.pi, 400)),
                            0.04 * np.sin(t), rng.uniform(-0.1, 0.1, 400)])
    neck = np.column_stack([0.012 * np.cos(t := rng.uniform(0, np.pi, 60)),
                            0.012 * np.sin(t), rng.uniform(-0.17, -0.1, 60)])
    stray = np.array([[0.0, 0.0, -0.5]])
    fit = ShapeFit("cylinder", np.zeros(3), np.array([0.0, 0.0, 1.0]), 0.04, 0.2, 0.001,
                   np.ones(461, bool), 0.001)
    lo, hi = axial_span(np.vstack([body, neck, stray]), fit)
    assert lo == pytest.approx(-0.17, abs=0.01)  # the lowest 1 % trimmed
    assert hi == pytest.approx(0.1, abs=1e-9)
    assert axial_span(body, fit) == pytest.approx((-0.1, 0.1))
    assert axial_span(body, replace(fit, shape="sphere")) is None


@pytest.mark.parametrize("label", ["box 8 x 5 x 15 cm, turned 30 deg", "ellipsoid 7 x 14 cm",
                                   "bottle 6.5 x 20 cm, neck down"])
def test_each_family_is_grasped_end_to_end(tmp_path: Path, label: str) -> None:
    """Every service a process over zenoh, lockstep, the sim holding the recording's own
    object: the pipeline grasps it."""
    _, wave, obj = next(f for f in FAMILIES if f[0] == label)
    rec = tmp_path / "family.mcap"
    generate(family_scenario(label, wave, obj, 24.0, 5), rec)
    out = tmp_path / "run"
    result = subprocess.run(wavegrasp_cmd("up", str(rec), "--pace", "lockstep", "--out",
                                          str(out)), capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, result.stdout[-3000:]
    outcomes = own_messages(out / "run.mcap", "wavegrasp/sim/outcome")
    shapes = {m["shape"] for m in own_messages(out / "run.mcap", "wavegrasp/perception/object")
              if m["centroid"]}
    assert shapes == {"box" if obj["family"] == "box" else "revolution"}
    assert any(o["success"] for o in outcomes), outcomes


def perceived_bottle(tmp_path: Path, seed: int, sea: tuple[float, float, float],
                     bottle: tuple[float, float, float, float, float, float], mount: dict,
                     camera: dict) -> Path:
    """Record 4 s of a bottle (diameter, length, neck diameter and length, mass, metres and
    kg; its rest height) in a sea (height, period, depth) and assert perception observes it
    in most frames within 3 mm of its volume centroid; return the recording."""
    d, length, neck_d, neck_length, mass, rest = bottle
    return recorded_and_perceived(tmp_path, seed, sea, {
        "family": "bottle", "diameter_m": d, "length_m": length, "neck_diameter_m": neck_d,
        "neck_length_m": neck_length, "mass_kg": mass, "rest_height_m": rest}, mount, camera)


def recorded_and_perceived(tmp_path: Path, seed: int, sea: tuple[float, float, float] | dict,
                           obj: dict, mount: dict, camera: dict, seconds: float = 4.0,
                           rmse_m: float = 0.003) -> Path:
    """Record ``seconds`` of an object (a scenario's ``object``) in a sea (height, period,
    depth, or a scenario's ``sea``) and assert perception observes it in most frames within
    ``rmse_m`` of its volume centroid; return the recording."""
    scenario = Scenario.model_validate({
        "name": f"{obj['family']}-{seed}", "seconds": seconds, "seed": seed,
        "sea": sea if isinstance(sea, dict) else dict(
            zip(("height_m", "period_s", "depth_m"), sea, strict=True)),
        "object": obj, "mount": mount, "camera": camera})
    generate(scenario, path := tmp_path / "object.mcap")
    ev = evaluate(path)
    assert ev.observed >= 0.9, ev.row()
    assert ev.rmse <= rmse_m, ev.row()
    return path


def test_a_small_bottle_far_from_the_camera_is_not_taken_for_a_box_seen_face_on(
        tmp_path: Path) -> None:
    """A 4 x 9 cm bottle 1.15 m from a 400 x 300 stereo camera (random-59-007): its near side
    lies within the depth noise of one plane, and taken for a box's face seen face-on it was
    refused in 443 frames of 450. A curved surface fits it three times better than that plane,
    so it is no face: observed in most frames, near its volume centroid."""
    perceived_bottle(
        tmp_path, 59007, (0.322, 1.768, 1.039), (0.0417, 0.0934, 0.0163, 0.0298, 0.0471, 0.6),
        {"position": [-0.0561, -0.271, 0.1399], "yaw_offset_deg": 23.53},
        {"eye": [-0.3423, 1.0728, 0.6349], "target": [0.0, 0.0, 0.6], "width": 400,
         "height": 300, "rate_hz": 15.0, "cloud": "organized"})


def test_a_squat_bottle_hanging_neck_down_seen_from_above_is_found_whole(
        tmp_path: Path) -> None:
    """An 11 x 11.5 cm bottle hanging neck down, 0.85 m from a camera 35 degrees above it
    (random-59-031): its shoulder faces away and is hidden, so its neck is a cluster of its
    own 3 cm below its body; and its flat base, 268 of 500 points, lies across the axis.
    The body alone put the centroid 15 mm high, and the base's points counted as the wall's
    pulled the axis 25 mm off (learnt 12-16 cm across: wider than the jaw). Now the neck is
    joined to the body and the base measured as a face: observed in most frames, within
    3 mm, as wide as it is."""
    path = perceived_bottle(
        tmp_path, 59031, (0.167, 0.873, 1.315), (0.1078, 0.1151, 0.0483, 0.0323, 0.4592, 0.667),
        {"position": [0.4715, 0.1905, 0.389], "yaw_offset_deg": -75.35},
        {"eye": [0.5533, -0.3163, 1.1892], "target": [0.0, 0.0, 0.667], "width": 256,
         "height": 192})
    fit = run_perception(path).last_fit
    assert fit is not None and 2 * fit.radius < 0.115, fit


def test_a_flat_ellipsoid_seen_from_the_side_is_fitted_upright(tmp_path: Path) -> None:
    """A 10.6 x 7.5 cm ellipsoid 1.3 m from a 5 Hz camera nearly level with it
    (random-7-011) fits about as near its points lying across the view, its depth taken for
    its height: its centroid was 16 mm near the camera. Hanging along its tether, it is now
    fitted upright: 17.6 mm and 54 % of frames before, 3.2 mm and 96 % now over these 10 s
    (4.1 mm over 30 s: the outline is 6-7 cm long, not 7.5, and its axis drifts 10°)."""
    recorded_and_perceived(
        tmp_path, 7011,
        {"height_m": 0.163, "period_s": 1.432, "depth_m": 1.167, "current_mps": 0.027,
         "current_deg": -102.6},
        {"family": "ellipsoid", "diameter_m": 0.1057, "length_m": 0.0745, "mass_kg": 0.1381,
         "rest_height_m": 0.565, "drag_coefficient": 0.5, "added_mass_coefficient": 0.5},
        {"position": [0.2384, -0.4346, 0.3395], "yaw_offset_deg": -150.65},
        {"eye": [1.1421, 0.619, 0.8408], "target": [0.0, 0.0, 0.565], "rate_hz": 5.0},
        seconds=10.0, rmse_m=0.005)


def test_a_thin_box_far_from_a_coarse_camera_is_learnt_as_a_box(tmp_path: Path) -> None:
    """A 4.2 x 2.8 x 30 cm box 1.6 m from a 256 x 192 camera (random-151-020): each face a
    few pixels wide, on an arc of any large circle. Outlines of 4-25 cm radius fitted it
    below its faces' RMS in one frame in three, it was learnt as a solid of revolution 14.8
    cm across (wider than the jaw opens; 17 % of frames observed, the centroid 62 mm off)
    and never grasped. An outline wider than the points spread across its axis is no solid
    that was seen: it is learnt as the box it is, near its volume centroid."""
    scenario = Scenario.model_validate({
        "name": "thin-box", "seconds": 6.0, "seed": 151020,
        "sea": {"height_m": 0.321, "period_s": 2.224, "depth_m": 1.19, "current_mps": 0.008,
                "current_deg": -31.8},
        "object": {"family": "box", "diameter_m": 0.0423, "length_m": 0.2995,
                   "depth_m": 0.0283, "turn_deg": 59.3, "mass_kg": 0.1248,
                   "rest_height_m": 0.461},
        "mount": {"position": [-0.514, 0.2044, 0.14], "yaw_offset_deg": 23.99},
        "camera": {"eye": [-1.4672, 0.3298, 0.9923], "target": [0.0, 0.0, 0.461],
                   "width": 256, "height": 192}})
    generate(scenario, path := tmp_path / "box.mcap")
    track = run_perception(path)
    fit = track.last_fit
    assert fit is not None and fit.shape == "box", fit
    assert sorted(fit.size) == pytest.approx([0.0283, 0.0423, 0.2995], abs=0.01)
    # Learnt in the first seconds; the last three are seen, near the volume centroid.
    truth = dict(zip(track.truth_ns.tolist(), track.truth, strict=True))
    stamps, centres = track.stamps_ns[-30:], track.centres[-30:]
    seen = ~np.isnan(centres[:, 0])
    errors = [c - truth[s] for s, c in zip(stamps[seen].tolist(), centres[seen], strict=True)]
    assert seen.mean() >= 0.8
    assert np.sqrt(np.mean(np.sum(np.square(errors), axis=1))) < 0.006

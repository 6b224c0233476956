"""Perception: accuracy against ground truth, bad input, and the service end to end."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from wavegrasp.perception.evaluate import evaluate, run_perception
from wavegrasp.perception.fit import ShapeFit
from wavegrasp.perception.main import PerceptionService, PerceptionSettings
from wavegrasp.perception.pipeline import joined, learnt_box
from wavegrasp.recording_io.reader import open_recording
from wavegrasp.recording_io.typestore import ros2_typestore
from wavegrasp.runtime.bus import CDR, Bus, Delivery
from wavegrasp.runtime.settings import Settings
from wavegrasp.schemas import ObjectObservation
from wavegrasp.wavetank.record import RecordConfig, generate

from conftest import wait_until


@pytest.mark.parametrize("config", [
    {"wave": 2, "object": "can_half"},
    {"wave": 1, "object": "buoy", "object_scale": 0.7},  # a sphere size it was not tuned on
    {"wave": 3, "object": "bottle", "object_scale": 1.5, "camera_offset": (-0.25, -0.2, 0.1)},
], ids=["can_half", "small-sphere", "large-bottle-moved-camera"])
def test_centroid_is_accurate_and_unbiased(config: dict, tmp_path: Path) -> None:
    path = tmp_path / "rec.mcap"
    generate(RecordConfig(seconds=6.0, seed=5, preroll_s=5.0, **config), path)
    ev = evaluate(path)
    assert ev.observed >= 0.95
    assert ev.rmse <= 0.005, f"RMSE {ev.rmse * 1e3:.2f} mm"
    assert np.linalg.norm(ev.bias) <= 0.003, f"bias {ev.bias * 1e3} mm"


def points_cdr(points: np.ndarray, frame_id: str = "trisect_optical", fields: str = "xyz",
               stamp_ns: int = 10**18) -> bytes:
    """A PointCloud2 as a camera driver would send it (float32 fields, 4 bytes apart)."""
    t = ros2_typestore()
    pf = t.types["sensor_msgs/msg/PointField"]
    header = t.types["std_msgs/msg/Header"](
        stamp=t.types["builtin_interfaces/msg/Time"](sec=stamp_ns // 10**9, nanosec=0),
        frame_id=frame_id)
    data = np.ascontiguousarray(points, dtype="<f4").reshape(-1)
    msg = t.types["sensor_msgs/msg/PointCloud2"](
        header=header, height=1, width=len(points),
        fields=[pf(name=n, offset=4 * i, datatype=7, count=1) for i, n in enumerate(fields)],
        is_bigendian=False, point_step=4 * len(fields), row_step=4 * len(fields) * len(points),
        data=data.view(np.uint8), is_dense=False)
    return t.serialize_cdr(msg, "sensor_msgs/msg/PointCloud2")


def test_bad_clouds_give_observation_less_frames_with_reasons(recording: Path) -> None:
    bus = Bus(Settings(service="perception", zenoh_mode="peer", zenoh_connect=[],
                       zenoh_listen=[]))
    try:
        service = PerceptionService(PerceptionSettings(service="perception"), bus=bus)
        seen: list[ObjectObservation] = []
        bus.subscribe("wavegrasp/perception/object", lambda m, d: seen.append(m),
                      ObjectObservation)
        routes = {key: i for i, key in enumerate(bus.subscriptions)}
        tf = next(m for m in open_recording(recording).messages() if m.topic == "/tf_static")

        def feed(key: str, payload: bytes) -> bool:
            return bus.dispatch(Delivery(key, payload, CDR, None, 0, routes[key]))

        rng = np.random.default_rng(0)
        far = rng.uniform(-1, 1, (500, 3)) + [0, 0, 20]  # nothing but far-away specks
        nan_cloud = np.full((100, 3), np.nan)
        assert feed("trisect/points", points_cdr(far[:10])) is True  # before tf: it waits
        assert feed("tf_static", tf.cdr) is True  # and is processed now
        assert feed("trisect/points", points_cdr(far[:10], frame_id="nowhere")) is True
        assert feed("trisect/points", points_cdr(np.zeros((0, 3)))) is True
        assert feed("trisect/points", points_cdr(nan_cloud)) is True
        assert feed("trisect/points", points_cdr(far[:, :2], fields="xy")) is False
        assert feed("trisect/points", points_cdr(far)) is False  # the first frame's stamp again
        assert feed("trisect/points", points_cdr(far, stamp_ns=10**18 + 10**9)) is True
        assert feed("trisect/points", b"\x00\x01\x00\x00 not a cloud") is False
        assert feed("tf_static", b"garbage") is False
        def all_seen() -> bool:
            while not bus.inbox.empty():
                bus.dispatch(bus.inbox.get())
            return len(seen) >= 8

        assert wait_until(all_seen, timeout=5), [m.reason for m in seen]
        reasons = [m.reason for m in seen]
        assert all(m.centroid is None for m in seen)
        assert reasons[0] == "no object-like cluster in the workspace"
        # A frame whose transform never comes is reported when the next frame arrives.
        assert reasons[1].startswith("unknown frame") and "nowhere" in reasons[1]
        assert reasons[2:4] == ["empty cloud", "empty cloud"]  # NaN points are dropped
        assert "no field z" in reasons[4]
        assert reasons[5] == f"duplicate: stamp {10**18} <= last {10**18}"
        assert reasons[6] == "no object-like cluster in the workspace"
        assert reasons[7].startswith("bad cloud")
        assert service.counters["nonfinite_points"] == 100
        assert bus.bad["trisect/points"] == 3 and bus.bad["tf_static"] == 1
    finally:
        bus.close()


def test_observations_carry_the_seabed_seen_in_the_cloud(recording: Path) -> None:
    """The seabed plane perception removes from the cloud goes out with each observation
    (the planner keeps the arm off it): the wave tank's floor is z = 0, normal up."""
    bus = Bus(Settings(service="perception", zenoh_mode="peer", zenoh_connect=[],
                       zenoh_listen=[]))
    try:
        PerceptionService(PerceptionSettings(service="perception"), bus=bus)
        seen: list[ObjectObservation] = []
        bus.subscribe("wavegrasp/perception/object", lambda m, d: seen.append(m),
                      ObjectObservation)
        routes = {key: i for i, key in enumerate(bus.subscriptions)}
        fed = 0
        for m in open_recording(recording).messages():
            if fed == 6:
                break
            if m.topic in ("/tf_static", "/trisect/points"):
                key = m.topic.lstrip("/")
                bus.dispatch(Delivery(key, m.cdr, CDR, None, 0, routes[key]))
                fed += key == "trisect/points"

        def all_seen() -> bool:
            while not bus.inbox.empty():
                bus.dispatch(bus.inbox.get())
            return len(seen) >= 5

        assert wait_until(all_seen, timeout=10)
        found = [m for m in seen if m.centroid is not None]
        assert found, [m.reason for m in seen]
        for m in found:
            assert m.seabed_normal is not None and m.seabed_offset_m is not None
            assert m.seabed_normal.z > 0.999 and abs(m.seabed_offset_m) < 0.01
    finally:
        bus.close()


def test_the_mesh_is_rebuilt_as_its_views_double_and_at_least_every_max_period() -> None:
    """The first mesh after 10 frames (1 s at 10 Hz), then one each time the frames in it
    have doubled, and at least one every 20 s once that is longer."""
    bus = Bus(Settings(service="perception", zenoh_mode="peer", zenoh_connect=[],
                       zenoh_listen=[]))
    try:
        service = PerceptionService(PerceptionSettings(service="perception"), bus=bus)
        starts = []
        rng = np.random.default_rng(0)
        ball = rng.normal(size=(400, 3))
        ball = 0.05 * ball / np.linalg.norm(ball, axis=1, keepdims=True)
        for frame in range(1, 701):
            service.accumulator.add(ball, np.zeros(3), np.eye(3))
            before = service._mesh_job
            service.start_mesh_if_due()
            if service._mesh_job is not before:
                starts.append(frame)
                service._mesh_job.result()
                service._mesh_job = None
        assert starts == [10, 30, 60, 120, 240, 440, 640]
    finally:
        bus.close()



def _upright_cylinder_cloud(rng: np.random.Generator, centre: np.ndarray, noise_m: float,
                            radius: float = 0.033, length: float = 0.122,
                            n: int = 6000) -> np.ndarray:
    """The near side of an upright cylinder's wall as a camera at the origin sees it (n, 3),
    metres, with ``noise_m`` along each ray."""
    th, h = rng.uniform(0, 2 * np.pi, n), rng.uniform(-length / 2, length / 2, n)
    radial = np.column_stack([np.cos(th), np.sin(th), np.zeros(n)])
    wall = centre + radius * radial + h[:, None] * [0.0, 0.0, 1.0]
    ray = wall / np.linalg.norm(wall, axis=1, keepdims=True)
    seen = np.einsum("ij,ij->i", radial, -ray) > 0.1
    return wall[seen] + rng.normal(0, noise_m, (seen.sum(), 1)) * ray[seen]


def test_a_fit_far_off_the_points_once_the_shape_is_learnt_is_not_reported() -> None:
    """Once learnt, a fit several times farther off the points than the learnt fits were is a
    failed one (a tilting cylinder's fit slid to a wrong axis: 57 mm off, 6 mm off its points,
    its sigma 1 mm), reported missing with why; a fit as good as the learnt ones is kept."""
    from wavegrasp.perception.fit import ShapeFit
    from wavegrasp.perception.pipeline import Perception, PerceptionConfig

    rng = np.random.default_rng(1)
    centre = np.array([0.0, 0.8, 0.0])  # level with the camera: both ends in view
    results = []
    for noise in (0.0015, 0.008):
        # A cap-less wall says little of where the ends are: not what is tested here.
        perception = Perception(PerceptionConfig(max_sigma_m=0.05))
        perception.prior = ShapeFit("cylinder", centre, np.array([0.0, 0.0, 1.0]), 0.033,
                                    0.122, 0.0012, np.ones(1, bool), 0.0)
        perception.track, perception.last_stamp_ns = centre.copy(), 100_000_000
        results.append(perception.process(_upright_cylinder_cloud(rng, centre, noise),
                                          np.eye(4), 200_000_000))
    kept, refused = results
    assert kept.fit is not None and np.linalg.norm(kept.fit.centre - centre) < 0.01
    assert refused.fit is None and refused.reason.startswith("fit failed: "), refused.reason
    assert "mm off the points, the learnt shape 1.2 mm" in refused.reason


def test_a_boxs_sizes_are_learnt_from_two_fits_that_disagree() -> None:
    """Two fits whose extents along one axis are far apart (one matched to another side):
    neither lies within a quarter of their median, and the size is still learnt, one of them."""
    def box(size: list[float]) -> ShapeFit:
        return ShapeFit("box", np.zeros(3), np.array([0.0, 0.0, 1.0]), 0.05, max(size), 0.001,
                        np.ones(10, bool), 0.002, frame=np.eye(3), size=np.array(size),
                        whole=np.ones(3, bool))
    fits = [box([0.06, 0.04, 0.29]), box([0.06, 0.29, 0.29])]
    size = learnt_box(fits, fits[0]).size
    assert size is not None
    np.testing.assert_allclose(size[[0, 2]], [0.06, 0.29])
    assert size[1] in (0.04, 0.29)


def test_a_part_near_the_object_is_joined_and_a_line_is_not() -> None:
    """A bottle's neck seen apart from its body (its shoulder hidden) is part of the object;
    what is left of the tether near it, a line, is not (joined, it stretched a bottle's
    outline by 4-9 cm)."""
    rng = np.random.default_rng(0)
    def wall(radius: float, z0: float, z1: float, n: int) -> np.ndarray:
        th, z = rng.uniform(-1.5, 1.5, n), rng.uniform(z0, z1, n)
        return np.column_stack([radius * np.cos(th), radius * np.sin(th), z])
    body, neck = wall(0.054, 0.0, 0.05, 400), wall(0.024, -0.065, -0.03, 30)
    line = np.column_stack([0.05 + rng.normal(0, 0.0015, (20, 2)) * [1, 0.2],
                            rng.uniform(-0.04, -0.005, 20)])
    whole = joined(body, [body, neck, line], 0.05, 0.004)
    assert len(whole) == len(body) + len(neck)
    assert len(joined(body, [body, neck], 0.02, 0.004)) == len(body)  # farther than the gap


def test_an_object_swaying_back_while_unseen_is_found_again() -> None:
    """Frames 0.8 s apart (a 5 Hz camera that missed three): the object has swung back, 25
    cm from where its track's straight line goes; it is searched for as far as its top
    speed of late could have taken it, and found."""
    from wavegrasp.perception.pipeline import Perception, PerceptionConfig

    rng = np.random.default_rng(2)
    perception = Perception(PerceptionConfig(max_sigma_m=0.05))  # a cap-less wall (above)
    perception.prior = ShapeFit("cylinder", np.zeros(3), np.array([0.0, 0.0, 1.0]), 0.033,
                                0.122, 0.0012, np.ones(1, bool), 0.0)
    def at(t: float) -> np.ndarray:  # a 15 cm sway of 1.9 s, 0.8 m in front of the camera
        return np.array([0.15 * np.sin(2 * np.pi * t / 1.9), 0.8, 0.0])
    for t in (0.0, 0.2, 0.4, 1.2):
        result = perception.process(_upright_cylinder_cloud(rng, at(t), 0.001), np.eye(4),
                                    int(1e9 + t * 1e9))
        assert result.fit is not None, (t, result.reason)
    assert np.linalg.norm(result.fit.centre - at(1.2)) < 0.01


def test_a_fast_swing_seen_at_5_hz_is_followed_through_its_turns() -> None:
    """A 15 cm swing of 1.2 s seen at 5 Hz moves up to 16 cm a frame and turns back within
    two frames: the track's straight line (a smoothed velocity) ran on past each turn (a
    real scene, random-97-006: 12-13 cm off at every turn, then lost for 3-4 frames of every
    swing). The parabola through its last three centroids follows it: every frame found."""
    from wavegrasp.perception.pipeline import Perception, PerceptionConfig

    rng = np.random.default_rng(3)
    perception = Perception(PerceptionConfig(max_sigma_m=0.05))  # a cap-less wall (above)
    perception.prior = ShapeFit("cylinder", np.zeros(3), np.array([0.0, 0.0, 1.0]), 0.033,
                                0.122, 0.0012, np.ones(1, bool), 0.0)
    def at(t: float) -> np.ndarray:
        return np.array([0.15 * np.sin(2 * np.pi * t / 1.2), 0.9, 0.0])
    missed = []
    for t in np.arange(0.0, 5.0, 0.2):
        result = perception.process(_upright_cylinder_cloud(rng, at(t), 0.001), np.eye(4),
                                    int(1e9 + t * 1e9))
        # Along the axis a cap-less wall says little (above): its swing is what is tested.
        if result.fit is None or np.linalg.norm(result.fit.centre[:2] - at(t)[:2]) > 0.01:
            missed.append((round(t, 1), result.reason))
    assert not missed


def test_a_window_holds_every_point_of_an_organized_cloud_within_its_sphere() -> None:
    from wavegrasp.perception.window import PixelRays
    from wavegrasp.wavetank.camera import TrisectCamera

    cam = TrisectCamera(np.eye(4), width=160, height=120)
    rng = np.random.default_rng(3)
    points = rng.uniform([-1.0, -0.8, 0.3], [1.0, 0.8, 2.5], (40_000, 3))
    in_view = (np.abs(points[:, :2] / points[:, 2:]) < [0.65, 0.5]).all(axis=1)
    image = cam.organize(points[in_view])
    xyz = image.reshape(cam.height, cam.width, 3)
    rays = PixelRays.learn(xyz)
    assert rays is not None and rays.margin_px < 3
    rows, cols = np.mgrid[0:cam.height, 0:cam.width]
    for _ in range(200):
        centre, radius = rng.uniform([-0.6, -0.5, 0.5], [0.6, 0.5, 2.2]), rng.uniform(0.02, 0.4)
        inside = np.linalg.norm(xyz - centre, axis=-1) < radius  # NaN pixels: False
        window = rays.window(centre, radius)
        if window is None:
            assert centre[2] <= radius
            continue
        r, c = window
        held = (rows >= r.start) & (rows < r.stop) & (cols >= c.start) & (cols < c.stop)
        assert not (inside & ~held).any()
        assert held.sum() < 0.8 * held.size or radius > 0.2  # a window, not the whole image
    scattered = rng.uniform(-1, 1, xyz.shape) + [0, 0, 2]  # points not on their pixels' rays
    assert PixelRays.learn(scattered.astype(np.float32)) is None


def test_organized_clouds_read_in_windows_give_the_observations_of_whole_frames(
        tmp_path: Path) -> None:
    """Following the object, perception reads only the pixels that can hold it, and finds
    exactly what it finds reading every frame whole; thinned, nearly so."""
    from wavegrasp.wavetank.scenario import CameraSpec, paper_scenario

    path = tmp_path / "organized.mcap"
    generate(paper_scenario(2, "can_half", seconds=4.0, seed=2, preroll_s=5.0,
                            camera=CameraSpec(width=336, height=188, rate_hz=15.0,
                                              cloud="organized")), path)
    messages = [m for m in open_recording(path).messages()
                if m.topic in ("/tf_static", "/trisect/points")]
    frames = sum(m.topic == "/trisect/points" for m in messages)
    observed = {}
    for windows in (True, False):
        observed[windows], read = observations(messages, frames, read_windows=windows,
                                               window_max_points=10**9)
        assert (read >= 0.8 * frames) if windows else read == 0, (read, frames)
    assert sum(o["centroid"] is not None for o in observed[False]) >= 0.8 * len(observed[False])
    assert observed[True] == observed[False]
    # Thinned to every s-th row and column (a camera's full resolution): fewer points, the
    # same object within a couple of millimetres.
    thin, read = observations(messages, frames, window_max_points=1500)
    assert read >= 0.8 * frames
    pairs = [(a, b) for a, b in zip(thin, observed[False], strict=True)
             if a["centroid"] is not None and b["centroid"] is not None]
    assert len(pairs) >= 0.8 * frames
    assert np.median([a["points_used"] / b["points_used"] for a, b in pairs]) < 0.5
    gaps = [np.linalg.norm([a["centroid"][k] - b["centroid"][k] for k in "xyz"])
            for a, b in pairs]
    assert np.median(gaps) < 0.002, np.median(gaps)
    # The offline evaluation reads the frames as the service does (its default settings).
    service_default, _ = observations(messages, frames)
    track = run_perception(path)
    offline = [None if np.isnan(c[0]) else [float(v) for v in c] for c in track.centres]
    assert offline == [None if o["centroid"] is None else [o["centroid"][k] for k in "xyz"]
                       for o in service_default]


def test_a_thinned_window_keeps_every_sth_row_and_column_within_its_pixel_budget() -> None:
    from wavegrasp.perception.window import thinned

    assert thinned((slice(10, 60), slice(20, 70)), 10_000) == (slice(10, 60, 1), slice(20, 70, 1))
    for rows, cols, budget in [(160, 156, 10_000), (376, 672, 10_000), (7, 3000, 100),
                               (101, 99, 2_500)]:
        r, c = thinned((slice(5, 5 + rows), slice(0, cols)), budget)
        assert r.step == c.step and (r.start, r.stop, c.stop) == (5, 5 + rows, cols)
        kept = len(range(rows)[::r.step]) * len(range(cols)[::r.step])
        smaller = len(range(rows)[::r.step - 1]) * len(range(cols)[::r.step - 1])
        assert kept <= budget and (r.step == 1 or smaller > budget), (rows, cols, r.step)
    with pytest.raises(ValueError, match="max_pixels"):
        thinned((slice(0, 10), slice(0, 10)), 0)


def observations(messages: list, frames: int, **settings) -> tuple[list[dict], int]:
    """A perception service's observations of recorded ``messages`` (their headers aside),
    and how many frames it read in a window."""
    bus = Bus(Settings(service="perception", zenoh_mode="peer", zenoh_connect=[],
                       zenoh_listen=[]))
    try:
        service = PerceptionService(PerceptionSettings(service="perception", **settings),
                                    bus=bus)
        seen: list[ObjectObservation] = []
        bus.subscribe("wavegrasp/perception/object", lambda m, d: seen.append(m),
                      ObjectObservation)
        routes = {key: i for i, key in enumerate(bus.subscriptions)}
        for m in messages:
            key = m.topic.lstrip("/")
            assert bus.dispatch(Delivery(key, m.cdr, CDR, None, 0, routes[key]))

        def all_seen() -> bool:
            while not bus.inbox.empty():
                bus.dispatch(bus.inbox.get())
            return len(seen) >= frames

        assert wait_until(all_seen, timeout=10)
        return ([m.model_dump(exclude={"header"}) for m in seen],
                service.counters["frames read in a window"])
    finally:
        bus.close()

"""The vehicle's edge stage: each camera frame cut down to the object's region and as much of
the rest as the tether's budget allows, the frame's sequence number and times kept."""

from __future__ import annotations

import numpy as np
import pytest

from wavegrasp.edge.main import EdgeService, EdgeSettings, object_region
from wavegrasp.edge.reduce import Region, frame_budget, keep_mask
from wavegrasp.recording_io.ros_msgs import decode_points, encode_points
from wavegrasp.runtime.bus import Delivery
from wavegrasp.runtime.trace import CdrAttachment
from wavegrasp.schemas import Header, ObjectObservation, Vec3

from conftest import wait_until


def scene(n: int = 40_000, seed: int = 0) -> np.ndarray:
    """A camera's view, metres, its frame: a seabed 1.5 m away and a ball 10 cm across at
    (0, 0, 1)."""
    rng = np.random.default_rng(seed)
    floor = np.column_stack([rng.uniform(-1, 1, n), rng.uniform(-1, 1, n), np.full(n, 1.5)])
    ball = rng.normal(size=(2000, 3))
    ball = 0.05 * ball / np.linalg.norm(ball, axis=1, keepdims=True) + [0.0, 0.0, 1.0]
    return np.vstack([floor, ball])


def test_the_objects_region_is_kept_whole_and_the_rest_thinned_to_the_budget() -> None:
    points = scene()
    region = Region(np.array([0.0, 0.0, 1.0]), 0.2)
    budget = 8000
    keep = keep_mask(points, region, budget, np.random.default_rng(1))
    inside = np.linalg.norm(points - region.centre, axis=1) <= region.radius_m
    assert keep[inside].all()  # 2000 points: within its share of the budget
    assert abs(keep.sum() - budget) < 300  # the rest fills the budget, in expectation
    # Without a region every point has the same chance.
    keep = keep_mask(points, None, budget, np.random.default_rng(1))
    assert abs(keep[inside].mean() - keep[~inside].mean()) < 0.05
    # A frame within the budget goes whole.
    assert keep_mask(points[:100], region, budget, np.random.default_rng(1)).all()


def test_a_region_bigger_than_the_budget_leaves_room_for_the_scene() -> None:
    points = scene()
    # Half the seabed in the region: the region gets its share (0.8), the rest the others.
    region = Region(np.array([-1.0, 0.0, 1.5]), 1.0)
    inside = np.linalg.norm(points - region.centre, axis=1) <= region.radius_m
    keep = keep_mask(points, region, 1000, np.random.default_rng(2))
    assert 720 < keep[inside].sum() < 880 and 120 < keep[~inside].sum() < 280


def test_the_budget_and_the_region_are_checked() -> None:
    assert frame_budget(8.0, 0.1) == (100_000 - 200) // 12  # 8 Mbit/s at 10 Hz
    with pytest.raises(ValueError, match="must be > 0"):
        frame_budget(0.0, 0.1)
    with pytest.raises(ValueError, match="region radius"):
        Region(np.zeros(3), 0.0)
    with pytest.raises(ValueError, match="region centre"):
        Region(np.array([0.0, np.nan, 0.0]), 1.0)
    with pytest.raises(ValueError, match="shape"):
        keep_mask(np.zeros((10, 2)), None, 5, np.random.default_rng(0))


def test_an_observation_places_a_ball_around_the_whole_object() -> None:
    obs = ObjectObservation(header=Header(stamp_ns=1), centroid=Vec3(x=1, y=2, z=3),
                            radius_m=0.05, length_m=0.3, axial_offset_m=0.02)
    centre, radius = object_region(obs, 0.2)
    np.testing.assert_allclose(centre, [1, 2, 3])
    assert radius == pytest.approx(0.15 + 0.02 + 0.2)
    assert object_region(ObjectObservation(header=Header(stamp_ns=1), reason="lost"), 0.2) is None


def test_the_service_forwards_each_frame_reduced_with_the_cameras_sequence_and_times(
        router) -> None:
    edge = EdgeService(EdgeSettings.from_env("edge", env=router.env, budget_mbit=4.0))
    camera, topside = router.bus("player"), router.bus("perception")
    got: list[Delivery] = []
    topside.subscribe("wavegrasp/edge/points", got.append)
    T_world_cam = np.eye(4)
    T_world_cam[:3, 3] = [0.0, 0.0, -1.0]
    edge.tf.update([("world", "cam", T_world_cam)])  # as tf_static would say
    try:
        # The object was seen at (0, 0, 0) in world: (0, 0, 1) in the camera's frame.
        topside.publish("wavegrasp/perception/object", ObjectObservation(
            header=Header(stamp_ns=10**9), centroid=Vec3(x=0, y=0, z=0), radius_m=0.05))
        assert wait_until(lambda: edge.drain() >= 0 and edge.region_world is not None)
        points = scene()
        cdr = encode_points(points, 10**9 + 10**8, "cam")
        seq = camera.publish_cdr("trisect/points", cdr, "sensor_msgs/msg/PointCloud2",
                                 log_time_ns=10**9 + 10**8)
        assert wait_until(lambda: edge.drain() >= 0 and topside.inbox.qsize() > 0)
        topside.dispatch(topside.inbox.get())
        (d,) = got
        att = CdrAttachment.decode(d.attachment)
        assert att is not None and att.seq == seq and att.log_time_ns == 10**9 + 10**8
        cloud = decode_points(d.payload)
        assert cloud.frame_id == "cam" and cloud.stamp_ns == 10**9 + 10**8
        assert frame_budget(4.0, 0.1) * 0.9 < len(cloud.points) < frame_budget(4.0, 0.1) * 1.1
        near = np.linalg.norm(cloud.points - [0.0, 0.0, 1.0], axis=1) < 0.06
        assert near.sum() == 2000  # every point of the ball
        assert edge.counters["frames with a region"] == 1
        # A cloud that is no cloud is counted, and the service goes on.
        camera.publish_cdr("trisect/points", b"\x00\x01\x00\x00junk",
                           "sensor_msgs/msg/PointCloud2")
        assert wait_until(lambda: edge.drain() >= 0 and edge.bus.bad["trisect/points"] == 1)
    finally:
        for bus in (edge.bus, camera, topside):
            bus.close()

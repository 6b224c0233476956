"""``wavegrasp edge``: on the vehicle, each camera frame cut down to what the tether carries.

Subscribes to the camera's clouds (``camera_key``), ``tf_static`` and perception's
observations (from topside: a few hundred bytes a frame), and publishes each frame on
``points_key`` with every point of the object's region (a ball around the last observed
centroid, in the camera's frame) and as many others, picked at random, as keep the stream
under ``budget_mbit`` (:mod:`wavegrasp.edge.reduce`). Each frame keeps the camera's
sequence number, publish time and log time, so perception and the recorder acknowledge and
time it as the camera's own. Frames leave as unorganized clouds (height 1).
"""

from __future__ import annotations

import numpy as np
from pydantic import Field

from wavegrasp.edge.reduce import Region, frame_budget, keep_mask
from wavegrasp.recording_io.ros_msgs import (
    Cloud,
    StaticTransforms,
    decode_tf,
    encode_points,
    view_points,
)
from wavegrasp.runtime.bus import BadMessage, Bus, Delivery
from wavegrasp.runtime.service import Service, service_main
from wavegrasp.runtime.settings import Settings
from wavegrasp.runtime.trace import CdrAttachment
from wavegrasp.schemas import ObjectObservation

OBJECT_KEY = "wavegrasp/perception/object"
POINT_CLOUD = "sensor_msgs/msg/PointCloud2"
#: Perception's largest object (PerceptionConfig.object_size_m): the region's size before
#: perception has said the object's own.
LARGEST_OBJECT_M = 0.40


class EdgeSettings(Settings):
    camera_key: str = Field("trisect/points", description="the camera's clouds")
    points_key: str = Field("wavegrasp/edge/points", description="the reduced clouds")
    budget_mbit: float = Field(12.0, gt=0, description="the reduced clouds' rate at most, "
                               "Mbit/s (wavegrasp up --tether: 0.6 of the tether's)")
    region_margin_m: float = Field(0.2, gt=0, description="the region reaches this far "
                                   "beyond the object: how far it moves between an "
                                   "observation and the frame after it reaches the vehicle")
    region_hold_s: float = Field(1.0, gt=0, description="an observation older than this "
                                 "(recording clock) places no region: the frame is "
                                 "thinned alike")
    seed: int = Field(0, description="the thinning's random picks")
    max_cloud_points: int = Field(2_000_000, gt=0, description="a bigger frame is refused "
                                  "unread")


def object_region(obs: ObjectObservation, margin_m: float) -> tuple[np.ndarray, float] | None:
    """The ball around an observed object: centre (3,), metres, world; radius, metres.
    None if the observation has no centroid."""
    if obs.centroid is None:
        return None
    sizes = [s for s in (obs.length_m, obs.breadth_m,
                         2 * obs.radius_m if obs.radius_m else None) if s]
    half = (max(sizes) if sizes else LARGEST_OBJECT_M) / 2 + abs(obs.axial_offset_m or 0.0)
    c = obs.centroid
    return np.array([c.x, c.y, c.z]), half + margin_m


class EdgeService(Service):
    subscribes_clock = False  # the frames' own stamps time everything here

    def __init__(self, settings: EdgeSettings, bus: Bus | None = None) -> None:
        super().__init__(settings, bus)
        self.cfg = settings
        self.tf = StaticTransforms()
        self.rng = np.random.default_rng(settings.seed)
        self.region_world: tuple[np.ndarray, float] | None = None
        self.region_stamp_ns = 0
        self._last_stamp_ns = 0
        self.period_s = 0.1  # until two frames have come: a 10 Hz camera
        self.bus.subscribe("tf_static", lambda d: self.tf.update(decode_tf(d.payload)))
        self.bus.subscribe(OBJECT_KEY, self.on_object, ObjectObservation)
        self.bus.subscribe(settings.camera_key, self.on_points)

    def on_object(self, obs: ObjectObservation, _d: Delivery) -> None:
        region = object_region(obs, self.cfg.region_margin_m)
        if region is not None and obs.header.stamp_ns >= self.region_stamp_ns:
            self.region_world, self.region_stamp_ns = region, obs.header.stamp_ns

    def region(self, cloud: Cloud) -> Region | None:
        """The object's region in the cloud's frame, if a fresh observation placed one."""
        age_s = (cloud.stamp_ns - self.region_stamp_ns) / 1e9
        if self.region_world is None or not -1.0 < age_s <= self.cfg.region_hold_s:
            return None
        try:
            T = self.tf.lookup(cloud.frame_id, "world")
        except ValueError:
            return None
        centre, radius = self.region_world
        return Region(T[:3, :3] @ centre + T[:3, 3], radius)

    def on_points(self, d: Delivery) -> None:
        try:
            att = CdrAttachment.decode(d.attachment)
            cloud = view_points(d.payload, max_points=self.cfg.max_cloud_points).points()
        except ValueError as exc:
            raise BadMessage(f"{d.key}: {exc}") from None
        if self._last_stamp_ns and 0 < cloud.stamp_ns - self._last_stamp_ns < 2e9:  # a gap
            # (or a replay begun again) is no camera's period
            self.period_s += 0.1 * ((cloud.stamp_ns - self._last_stamp_ns) / 1e9 - self.period_s)
        self._last_stamp_ns = cloud.stamp_ns
        region = self.region(cloud)
        keep = keep_mask(cloud.points, region, frame_budget(self.cfg.budget_mbit, self.period_s),
                         self.rng)
        out = encode_points(cloud.points[keep], cloud.stamp_ns, cloud.frame_id)
        self.bus.publish_cdr(self.cfg.points_key, out, POINT_CLOUD,
                             log_time_ns=cloud.stamp_ns, source=att)
        c = self.counters
        c["frames"] += 1
        c["frames with a region"] += region is not None
        c["points in"] += len(cloud.points)
        c["points out"] += int(keep.sum())
        c["bytes in"] += len(d.payload)
        c["bytes out"] += len(out)


def main(argv: list[str] | None = None) -> int:
    return service_main("edge", __doc__, EdgeSettings, EdgeService, argv)

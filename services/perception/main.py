"""``wavegrasp perception``: camera clouds (``points_key``) + ``tf_static`` -> the object.

Publishes one ``wavegrasp/perception/object`` per camera frame: the volume centroid in
``world`` with its uncertainty, or no centroid and the reason (empty cloud, unknown frame, no
object...); with a centroid, also the object's points on ``wavegrasp/perception/points``.
Whenever the frames it has seen have doubled (every ``mesh_period_s`` to
``mesh_max_period_s``), it rebuilds the object's closed mesh from the points of all frames so
far, on a worker thread off the per-frame path, and publishes it on
``wavegrasp/perception/mesh``; the frames' acknowledgements wait for that mesh, so in a
lockstep run everyone downstream gets it at the same frame every time. It never reads the
ground truth.
"""

from __future__ import annotations

import ctypes
import logging
import multiprocessing as mp
import signal
from concurrent.futures import Future, ProcessPoolExecutor

import numpy as np
from pydantic import Field

from wavegrasp.arm.transforms import frame_along
from wavegrasp.checks import StampOrder
from wavegrasp.perception.fit import ShapeFit
from wavegrasp.perception.mesh import MeshAccumulator, build_mesh, mesh_volume
from wavegrasp.perception.pipeline import FrameResult, Perception
from wavegrasp.perception.window import WindowReader
from wavegrasp.recording_io.ros_msgs import (
    Cloud,
    CloudView,
    StaticTransforms,
    decode_tf,
    encode_points,
    view_points,
)
from wavegrasp.runtime.bus import Bus, Delivery
from wavegrasp.runtime.placement import background_thread
from wavegrasp.runtime.service import Service, service_main
from wavegrasp.runtime.settings import Settings
from wavegrasp.runtime.trace import CdrAttachment, new_header
from wavegrasp.schemas import Header, Hop, ObjectMesh, ObjectObservation, Vec3
from wavegrasp.schemas.mesh_codec import encode_mesh

log = logging.getLogger("wavegrasp.perception")
OBJECT_KEY = "wavegrasp/perception/object"
#: The points taken as the object's, in ``world`` (a PointCloud2, CDR: what viewers show).
POINTS_KEY = "wavegrasp/perception/points"
MESH_KEY = "wavegrasp/perception/mesh"


class PerceptionSettings(Settings):
    points_key: str = Field("trisect/points", description="the camera's clouds (across a "
                            "tether, the edge's: wavegrasp/edge/points)")
    mesh_period_s: float = Field(2.0, description="the least between rebuilds (counted in "
                                 "frames at 10 Hz)")
    mesh_max_period_s: float = Field(20.0, description="later rebuilds wait as many frames "
                                     "as the mesh already holds, up to this: each then adds "
                                     "as many views again, at a fraction of the CPU (a "
                                     "rebuild every 2 s was a fifth of the service's)")
    mesh_min_frames: int = 10
    worker_cpus: str = Field("", description="CPUs of the mesh worker thread (a Linux CPU "
                             "list); empty: the service's own")
    max_cloud_points: int = Field(2_000_000, gt=0, description="a bigger camera frame (width "
                                  "x height) is refused unread: the camera sends ~40k points")
    read_windows: bool = Field(True, description="while the object is followed, read of an "
                               "organized cloud only the pixels that can hold it "
                               "(perception/window.py); false: every frame whole")
    window_max_points: int = Field(10_000, ge=1, description="a window that would hold more "
                                   "points (judged by the last one read) is read at every "
                                   "s-th row and column, s the least that leaves at most "
                                   "this many: a near object at a camera's full resolution")


def observation(header: Header, fit: ShapeFit, points_used: int,
                span: tuple[float, float] | None = None,
                seabed: np.ndarray | None = None) -> ObjectObservation:
    """The observation of a frame whose object was fitted with ``fit`` from ``points_used``
    points; a box's also carries its faces across its axis. ``span``: where it ends along
    its axis, metres from its centroid (:func:`~wavegrasp.perception.pipeline.axial_span`;
    None: the fit's length either side of it). ``seabed``: the seabed plane found in the
    cloud, (a, b, c, d), world, unit normal towards the water (the planner keeps the arm
    off it); None if none was."""
    quality = min(1.0, points_used / 150) * min(1.0, 0.003 / max(fit.rms, 1e-6))
    box = {}
    if fit.frame is not None and fit.size is not None:
        thin, broad = np.argsort(fit.size)[:2]  # the two extents across the longest
        box = {"side": Vec3.of(fit.frame[:, thin]), "side_width_m": float(fit.size[thin]),
               "breadth_m": float(fit.size[broad])}
    return ObjectObservation(
        header=header, centroid=Vec3.of(fit.centre), points_used=points_used, quality=quality,
        sigma_m=fit.sigma, shape=fit.shape, axis=Vec3.of(fit.axis), radius_m=fit.radius,
        length_m=fit.length if span is None else span[1] - span[0],
        axial_offset_m=(span[0] + span[1]) / 2 if span else None, fit_rms_m=fit.rms,
        seabed_normal=None if seabed is None else Vec3.of(seabed[:3]),
        seabed_offset_m=None if seabed is None else float(seabed[3]), **box)


PR_SET_PDEATHSIG = 1


def mesh_worker_setup(cpus: str) -> None:
    """Meshing (a few hundred ms of CPU every ``mesh_period_s``) yields the cores to the
    per-frame work: it runs under the normal policy, niced, and on its own CPUs when
    ``cpus`` names any."""
    warning = background_thread(10, cpus, "WAVEGRASP_WORKER_CPUS")
    if warning:
        log.warning("mesh worker: %s", warning)


def start_mesh_worker(cpus: str) -> None:
    """The mesh worker process's start: :func:`mesh_worker_setup`, and an end with the
    service's however that comes (a killed service leaves no worker behind)."""
    ctypes.CDLL(None, use_errno=True).prctl(PR_SET_PDEATHSIG, signal.SIGKILL)
    mesh_worker_setup(cpus)


def mesh_job(points: np.ndarray, weights: np.ndarray,
             frames: int) -> tuple[np.ndarray, np.ndarray, int]:
    """:func:`build_mesh` on the worker: vertices, triangles and the frames they are from."""
    return (*build_mesh(points, weights=weights), frames)


class PerceptionService(Service):
    def __init__(self, settings: PerceptionSettings, bus: Bus | None = None) -> None:
        # Meshing in a process of its own: in a thread it held the interpreter lock in C for
        # up to 24 ms at a time (kd-tree pairs, the hull), and camera frames waited that long
        # for perception to take them in. Forked now, before the bus starts its threads.
        self._executor = ProcessPoolExecutor(max_workers=1, mp_context=mp.get_context("fork"),
                                             initializer=start_mesh_worker,
                                             initargs=(settings.worker_cpus,))
        self._executor.submit(int).result()
        super().__init__(settings, bus)
        self.cfg = settings
        self.perception = Perception()
        self.tf = StaticTransforms()
        self.accumulator = MeshAccumulator()
        self._mesh_job: Future | None = None
        self._next_mesh_frame = settings.mesh_min_frames
        self._seq = 0
        self._order = StampOrder(restart_s=1.0)  # a replay begun again restarts the stream
        self._waiting: Delivery | None = None  # a frame whose transform has not come yet
        self._held_acks: list[tuple[Header, int, int]] = []  # frames after a mesh job began
        self.reader = WindowReader(settings.read_windows, settings.window_max_points)
        self.bus.subscribe("tf_static", self.on_tf)
        self.bus.subscribe(settings.points_key, self.on_points)

    def on_tf(self, d: Delivery) -> None:
        self.tf.update(decode_tf(d.payload))
        if self._waiting is not None:  # tf_static and the first frame arrive together
            waiting, self._waiting = self._waiting, None
            self.on_points(waiting)

    def header(self, d: Delivery, stamp_ns: int) -> Header:
        """Trace: the source's publish time (CDR attachment), then this service's receipt."""
        att = CdrAttachment.decode(d.attachment)
        self._seq += 1
        hops = [Hop(service="source", recv_ns=att.source_ns, sent_ns=att.source_ns)] if att else []
        return Header(seq=att.seq if att else self._seq, stamp_ns=stamp_ns, frame_id="world",
                      trace=[*hops, Hop(service=self.name, recv_ns=d.recv_ns)])

    def on_points(self, d: Delivery) -> None:
        """Process one camera frame; acknowledge it whatever came of it (the lockstep chain).

        A frame whose camera transform is not known yet waits for ``tf_static`` (zenoh may
        hand over the first frame before the transform sent just ahead of it) until the next
        frame comes; then it is reported without a centroid.
        """
        if self._waiting is not None:
            waiting, self._waiting = self._waiting, None
            self.on_points_now(waiting, wait_for_tf=False)
        self.on_points_now(d, wait_for_tf=True)

    def on_points_now(self, d: Delivery, wait_for_tf: bool) -> None:
        try:
            if self.process_frame(d, wait_for_tf):
                self._waiting = d
                return
        finally:
            try:
                att = CdrAttachment.decode(d.attachment)
            except ValueError:
                att = None  # counted as a bad message already; no frame to acknowledge
            if att is not None and self._waiting is not d:
                self.start_mesh_if_due()
                self._held_acks.append((Header(
                    seq=att.seq, stamp_ns=att.log_time_ns, frame_id="world",
                    trace=[Hop(service="source", recv_ns=att.source_ns,
                               sent_ns=att.source_ns)]), d.recv_ns, att.seq))
                if self._mesh_job is None:
                    self.release_acks()

    def release_acks(self) -> None:
        for header, recv_ns, seq in self._held_acks:
            self.ack_frame(header, recv_ns, seq)
        self._held_acks.clear()

    def process_frame(self, d: Delivery, wait_for_tf: bool = False) -> bool:
        """Process a frame; True if it has to wait for its camera transform."""
        try:
            cloud = self.read(view_points(d.payload, max_points=self.cfg.max_cloud_points))
        except ValueError as exc:
            self.publish_missing(new_header(self.name, 0, self.clock.now_ns()), f"bad cloud: {exc}")
            raise
        header = self.header(d, cloud.stamp_ns)
        if cloud.dropped_nonfinite:
            self.counters["nonfinite_points"] += cloud.dropped_nonfinite
        if not len(cloud.points):
            self.publish_missing(header, "empty cloud")
            return False
        try:
            T = self.tf.lookup("world", cloud.frame_id)
        except ValueError as exc:
            if wait_for_tf:
                self._seq -= 1  # the header is made again when it is processed
                return True
            self.publish_missing(header, f"unknown frame: {exc}")
            return False
        try:  # an older or repeated frame would drag the track back
            self._order.check(cloud.stamp_ns)
        except ValueError as exc:
            self.publish_missing(header, str(exc))
            raise
        result = self.perception.process(cloud.points, T, cloud.stamp_ns)
        if result.fit is None:
            self.publish_missing(header, result.reason or "no object")
            return False
        self.publish_observation(header, result, len(cloud.points))
        self.bus.publish_cdr(POINTS_KEY, encode_points(result.points, cloud.stamp_ns, "world"),
                             "sensor_msgs/msg/PointCloud2", log_time_ns=cloud.stamp_ns)
        if self.perception.prior is not None:
            self.accumulator.add(result.points, result.fit.centre, frame_along(result.fit.axis))
        return False

    def read(self, view: CloudView) -> Cloud:
        """A frame's finite points as perception needs them (:class:`WindowReader`)."""
        if not view.organized:
            return view.points()
        try:
            T = self.tf.lookup("world", view.frame_id)
        except ValueError:
            T = None
        cloud, windowed = self.reader.read(view, self.perception.search_region(view.stamp_ns), T)
        if windowed:
            self.counters["frames read in a window"] += 1
        return cloud

    def publish_missing(self, header: Header, reason: str) -> None:
        self.counters[f"missing: {reason.split(':')[0]}"] += 1
        self.bus.publish(OBJECT_KEY, ObjectObservation(header=header, reason=reason))

    def publish_observation(self, header: Header, result: FrameResult, n_points: int) -> None:
        assert result.fit is not None
        self.counters["observed"] += 1
        self.bus.publish(OBJECT_KEY, observation(header, result.fit, len(result.points),
                                                 result.span, self.perception.seabed))

    def start_mesh_if_due(self) -> None:
        """Rebuild the mesh on the worker once the frames in it have doubled, at least every
        ``mesh_max_period_s`` and at most every ``mesh_period_s`` (from the frame count, not
        the wall clock, so a lockstep run builds the same meshes)."""
        if self._mesh_job is not None or self.accumulator.frames < self._next_mesh_frame:
            return
        acc = self.accumulator
        wait = min(acc.frames, int(10 * self.cfg.mesh_max_period_s))
        self._next_mesh_frame = acc.frames + max(int(10 * self.cfg.mesh_period_s), wait)
        points, weights, frames = acc.points_object(), acc.counts(), acc.frames
        self._mesh_job = self._executor.submit(mesh_job, points, weights, frames)

    def on_tick(self) -> None:
        job = self._mesh_job
        if job is not None and job.done():
            self._mesh_job = None
            try:
                self.publish_mesh(*job.result())
            except ValueError as exc:  # too few or degenerate points: the next one may do
                self.counters["mesh failed"] += 1
                log.warning("mesh from %d frames failed: %s", self.accumulator.frames, exc)
            self.release_acks()

    def publish_mesh(self, vertices: np.ndarray, triangles: np.ndarray, frames: int) -> None:
        prior = self.perception.prior
        encoded = encode_mesh(vertices, triangles)
        self.bus.publish(MESH_KEY, ObjectMesh(
            header=new_header(self.name, frames, self.clock.now_ns(), frame_id="object"),
            shape=prior.shape if prior else "sphere", volume_m3=mesh_volume(vertices, triangles),
            frames=frames, **encoded))
        self.counters["meshes"] += 1

    def on_stop(self) -> None:
        # A mesh still being built is not waited for: at exit multiprocessing joins its
        # children, and a stopped perception waited on its busy worker past the launcher's
        # 10 s and was killed (a CI run on a loaded machine). The executor has no public way
        # to end a running worker before Python 3.14 (kill_workers); shutdown forgets them.
        workers = list((getattr(self._executor, "_processes", None) or {}).values())
        self._executor.shutdown(wait=False, cancel_futures=True)
        for worker in workers:
            worker.kill()


def main(argv: list[str] | None = None) -> int:
    return service_main("perception", __doc__, PerceptionSettings, PerceptionService, argv)

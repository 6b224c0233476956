"""What the pipeline saw and decided, as a rerun recording (``run.rrd``) and, if asked, live.

No bus here: :class:`RerunLog` takes decoded messages (the recorder hands them over). One
timeline, ``recording``: each message's capture time on the recording clock. Entities:

- ``world/cloud``: the camera's cloud in ``world``, decimated to ``max_cloud_points``;
- ``world/object/points``: the points perception took as the object's;
- ``world/object/centroid`` and ``world/object/track``: the tracked centroid and its recent path;
- ``world/object/truth`` and ``world/object/truth_track``: the ground truth (generated
  recordings);
- ``world/prediction/path`` and ``world/prediction/sigma``: the predicted path, wireframe
  spheres of one sigma (at most 5 cm) along it;
- ``world/plan/candidates``, ``world/plan/grasp``, ``world/plan/path``: grasp poses checked
  (approach arrows), the chosen one, and the planned tool path;
- the arm from its URDF on its ``tf_static`` mount, its joints from ``wavegrasp/sim/arm_state``;
- ``gate/mean_error_mm``, ``gate/threshold_mm``, ``gate/go``; ``latency/<hop>`` (ms, from each
  decision's trace); ``log/decisions`` and ``log/outcomes`` (text).

A blueprint opens the file on the scene beside the gate, latency and log panels.
"""

from __future__ import annotations

import logging
import uuid
from collections import deque
from pathlib import Path

import numpy as np
import rerun as rr
import rerun.blueprint as rrb
from rerun.urdf import UrdfTree
from scipy.spatial.transform import Rotation

from wavegrasp.runtime.trace import hop_times_ms
from wavegrasp.schemas import (
    ArmState,
    GateDecision,
    GraspOutcome,
    GraspPlan,
    MotionPrediction,
    ObjectObservation,
    Pose,
)

log = logging.getLogger("wavegrasp.recorder")
TIMELINE = "recording"
TRACK_LENGTH = 100  # centroids and truths kept in the track lines


def blueprint() -> rrb.Blueprint:
    return rrb.Blueprint(
        rrb.Horizontal(
            rrb.Spatial3DView(name="scene", origin="/"),
            rrb.Vertical(
                rrb.TimeSeriesView(name="gate: mean error against threshold (mm)",
                                   origin="gate"),
                rrb.TimeSeriesView(name="latency per hop (ms)", origin="latency"),
                rrb.TextLogView(name="decisions and outcomes", origin="log"),
            ),
            column_shares=[3, 2],
        ),
        collapse_panels=True,
    )


class RerunLog:
    """path : the ``.rrd`` to write (None: none); urdf : the arm's description;
    viewer_url : also stream live to this viewer (``rerun+http://HOST:PORT/proxy``)."""

    def __init__(self, path: Path | None, urdf: Path, viewer_url: str | None = None,
                 max_cloud_points: int = 4000) -> None:
        self.rec = rr.RecordingStream("wavegrasp", recording_id=uuid.uuid4())
        sinks: list = [rr.FileSink(str(path))] if path is not None else []
        if viewer_url:
            sinks.append(rr.GrpcSink(viewer_url))
        self.rec.set_sinks(*sinks, default_blueprint=blueprint())
        self.max_cloud_points = max_cloud_points
        self.urdf = UrdfTree.from_file_path(str(urdf))
        self.urdf.log_urdf_to_recording(self.rec)
        self._joints = {j.name: j for j in self.urdf.joints()}
        self._mounted = False
        self._track: deque[np.ndarray] = deque(maxlen=TRACK_LENGTH)
        self._truth: deque[np.ndarray] = deque(maxlen=TRACK_LENGTH)
        self._truth_at = -(1 << 62)
        self.truth_period_ns = 100_000_000

    def _at(self, stamp_ns: int) -> None:
        self.rec.set_time(TIMELINE, timestamp=np.datetime64(int(stamp_ns), "ns"))

    # --- the scene ----------------------------------------------------------------------

    def mount(self, T_world_base: np.ndarray) -> None:
        """Where the arm's base link is (4, 4), world; logged once."""
        if self._mounted:
            return
        self._mounted = True
        self.rec.log("world/arm_mount", rr.Transform3D(
            translation=T_world_base[:3, 3],
            quaternion=Rotation.from_matrix(T_world_base[:3, :3]).as_quat(),
            parent_frame="tf#/world", child_frame=self.urdf.root_link().name), static=True)

    def cloud(self, stamp_ns: int, points: np.ndarray) -> None:
        """points : array, shape (n, 3), metres, world; every k-th is kept."""
        step = max(1, -(-len(points) // self.max_cloud_points))
        self._at(stamp_ns)
        self.rec.log("world/cloud", rr.Points3D(points[::step], radii=0.002,
                                                colors=[150, 150, 160]))

    def object_points(self, stamp_ns: int, points: np.ndarray) -> None:
        self._at(stamp_ns)
        self.rec.log("world/object/points", rr.Points3D(points, radii=0.003,
                                                        colors=[255, 140, 0]))

    def truth(self, stamp_ns: int, position: np.ndarray) -> None:
        """Logged at most every ``truth_period_ns`` (ground truth comes at 100 Hz)."""
        if stamp_ns - self._truth_at < self.truth_period_ns:
            return
        self._truth_at = stamp_ns
        self._at(stamp_ns)
        self._truth.append(position)
        self.rec.log("world/object/truth", rr.Points3D([position], radii=0.006,
                                                       colors=[255, 255, 255]))
        self.rec.log("world/object/truth_track", rr.LineStrips3D(
            [np.array(self._truth)], radii=0.001, colors=[200, 200, 200]))

    # --- the pipeline's messages --------------------------------------------------------

    def observation(self, msg: ObjectObservation) -> None:
        if msg.centroid is None:
            return
        c = np.array([msg.centroid.x, msg.centroid.y, msg.centroid.z])
        self._track.append(c)
        self._at(msg.header.stamp_ns)
        self.rec.log("world/object/centroid", rr.Points3D([c], radii=0.008,
                                                          colors=[40, 200, 80]))
        self.rec.log("world/object/track", rr.LineStrips3D([np.array(self._track)],
                                                           radii=0.0015, colors=[40, 200, 80]))

    def prediction(self, msg: MotionPrediction) -> None:
        p = np.array([[s.x, s.y, s.z] for s in msg.samples])
        sigma = np.array([s.sigma for s in msg.samples])
        self._at(msg.header.stamp_ns)
        self.rec.log("world/prediction/path", rr.LineStrips3D([p], radii=0.0015,
                                                              colors=[60, 120, 255]))
        every = slice(None, None, max(1, len(p) // 10))
        self.rec.log("world/prediction/sigma", rr.Ellipsoids3D(
            centers=p[every], half_sizes=np.repeat(np.clip(sigma[every], 0.001, 0.05)[:, None],
                                                   3, axis=1),
            colors=[60, 120, 255], fill_mode=rr.components.FillMode.MajorWireframe))

    def plan(self, msg: GraspPlan) -> None:
        self._at(msg.header.stamp_ns)
        if msg.candidates:
            origins, vectors = _approach_arrows(msg.candidates)
            self.rec.log("world/plan/candidates", rr.Arrows3D(
                origins=origins, vectors=vectors, colors=[170, 170, 170]))
        origins, vectors = _approach_arrows([msg.grasp])
        self.rec.log("world/plan/grasp", rr.Arrows3D(origins=origins, vectors=vectors,
                                                     colors=[230, 40, 40], radii=0.004))
        if msg.cartesian_path:
            self.rec.log("world/plan/path", rr.LineStrips3D(
                [[[s.x, s.y, s.z] for s in msg.cartesian_path]], radii=0.002,
                colors=[230, 40, 40]))

    def decision(self, msg: GateDecision) -> None:
        self._at(msg.header.stamp_ns)
        if msg.mean_error_m is not None:
            self.rec.log("gate/mean_error_mm", rr.Scalars(msg.mean_error_m * 1e3))
        self.rec.log("gate/threshold_mm", rr.Scalars(msg.threshold_m * 1e3))
        self.rec.log("gate/go", rr.Scalars(1.0 if msg.go else 0.0))
        self.rec.log("log/decisions", rr.TextLog(
            f"{'GO' if msg.go else 'no-go'} {msg.plan_id}: {msg.reason}",
            level="INFO" if msg.go else "DEBUG"))
        trace = msg.header.trace
        try:
            hops = hop_times_ms(trace)
        except ValueError:
            return  # `wavegrasp latency` names the hop; nothing to plot
        for name, ms in hops:
            self.rec.log(f"latency/{name.replace(' -> ', '_to_')}", rr.Scalars(ms))
        if trace:
            self.rec.log("latency/end_to_end",
                         rr.Scalars((trace[-1].sent_ns - trace[0].sent_ns) / 1e6))

    def arm_state(self, msg: ArmState) -> None:
        self._at(msg.header.stamp_ns)
        values = dict(zip(msg.joint_names, msg.positions, strict=True))
        fingers = [j for j in self._joints.values() if j.joint_type == "prismatic"]
        for finger in fingers:  # the jaw's opening shared between its fingers
            values[finger.name] = msg.jaw_opening_m / len(fingers)
        for name, value in values.items():
            joint = self._joints.get(name)
            if joint is not None:
                if joint.limit_lower < joint.limit_upper:  # rerun's own clamp warns each time:
                    # a jaw wide open is a rounding past its limit at every state
                    value = min(max(value, joint.limit_lower), joint.limit_upper)
                self.rec.log("world/arm_joints", joint.compute_transform(value))

    def outcome(self, msg: GraspOutcome) -> None:
        self._at(msg.header.stamp_ns)
        text = (f"trial {msg.trial} attempt {msg.attempt}: "
                f"{'success' if msg.success else msg.failure} ({msg.plan_id})")
        self.rec.log("log/outcomes", rr.TextLog(text, level="INFO" if msg.success else "WARN"))

    def close(self) -> None:
        """Flush and close; a viewer that went away first costs only its own stream."""
        try:
            self.rec.flush(timeout_sec=5.0)
        except RuntimeError as exc:  # the gRPC sink's connection severed
            log.warning("live viewer: %s", exc)
        self.rec.disconnect()


def _approach_arrows(poses: list[Pose], length: float = 0.06) -> tuple[np.ndarray, np.ndarray]:
    """Arrows (origins, vectors), shape (n, 3), along each grasp's approach (tool z) ending
    at its grasp point."""
    p = np.array([[x.position.x, x.position.y, x.position.z] for x in poses])
    q = np.array([[x.orientation.x, x.orientation.y, x.orientation.z, x.orientation.w]
                  for x in poses])
    z = Rotation.from_quat(q).as_matrix()[:, :, 2] * length
    return p - z, z

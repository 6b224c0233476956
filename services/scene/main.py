"""``wavegrasp scene``: the grasp as Foxglove's 3D panel and rviz2 draw it.

From the bus it makes, in the recording's time:
- ``tf`` (``tf2_msgs/msg/TFMessage``): the arm's links from each ``joint_states`` (its base
  placed by the recording's ``tf_static``), and ``object``, the tracked object's frame
  (origin at its volume centroid, z along its axis) from each observation;
- ``robot_description`` (``std_msgs/msg/String``): the arm's URDF, again every
  ``description_period_s`` (ROS latches it; a viewer that joins late gets it);
- ``wavegrasp/scene/mesh`` (``visualization_msgs/msg/MarkerArray``): the object's mesh, in
  ``object``;
- ``wavegrasp/scene/markers`` (``visualization_msgs/msg/MarkerArray``): the object's
  centroid, the prediction with its sigma at the end, the grasp pose and the approach
  path of the latest plan, and the gate's verdict (its error against ε) over the object;
- ``wavegrasp/scene/latency`` (:class:`~wavegrasp.schemas.DecisionLatency`): each gate
  decision's milliseconds per hop, from its trace, for plots.
The recorder writes them into run.mcap like every channel; ``wavegrasp foxglove`` serves them
live. It reads only what the pipeline publishes.
"""

from __future__ import annotations

import time

import numpy as np
from pydantic import Field
from scipy.spatial.transform import Rotation

from wavegrasp.arm import ArmModel
from wavegrasp.arm.transforms import frame_along
from wavegrasp.recording_io.joint_cdr import decode_joint_state
from wavegrasp.runtime.bus import BadMessage, Bus, Delivery
from wavegrasp.runtime.service import Service, service_main
from wavegrasp.runtime.settings import Settings
from wavegrasp.runtime.trace import hop_times_ms, new_header
from wavegrasp.scene import markers as mk
from wavegrasp.schemas import (
    DESCRIPTION_KEY,
    MARKERS_KEY,
    MESH_KEY,
    TF_KEY,
    DecisionLatency,
    GateDecision,
    GraspPlan,
    MotionPrediction,
    ObjectMesh,
    ObjectObservation,
    Pose,
)
from wavegrasp.schemas.mesh_codec import decode_mesh

LATENCY_KEY = "wavegrasp/scene/latency"
GREEN, RED, BLUE, ORANGE, GREY = ((0.2, 0.8, 0.3, 1.0), (0.9, 0.2, 0.2, 1.0),
                                  (0.2, 0.5, 1.0, 0.8), (1.0, 0.6, 0.1, 1.0),
                                  (0.7, 0.7, 0.7, 0.6))


class SceneSettings(Settings):
    arm_urdf: str | None = Field(None, description="the arm's URDF (default: ours)")
    joint_states_key: str = "joint_states"
    description_period_s: float = Field(2.0, gt=0)


def pose_matrix(p: Pose) -> np.ndarray:
    T = np.eye(4)
    q = p.orientation
    T[:3, :3] = Rotation.from_quat([q.x, q.y, q.z, q.w]).as_matrix()
    T[:3, 3] = [p.position.x, p.position.y, p.position.z]
    return T


class SceneService(Service):
    subscribes_clock = False

    def __init__(self, settings: SceneSettings, bus: Bus | None = None) -> None:
        self.arm = ArmModel.load(settings.arm_urdf or None)
        super().__init__(settings, bus)
        self.cfg = settings
        assert self.arm.urdf_path is not None
        self.description = mk.text_message(self.arm.urdf_path.read_text())
        self._described_at = 0.0
        self.centroid: np.ndarray | None = None
        self.latencies = 0  # DecisionLatency messages published
        self.latest: dict[str, object] = {}  # per marker namespace, its latest marker
        b = self.bus
        b.subscribe(settings.joint_states_key, self.on_joint_state)
        b.subscribe("wavegrasp/perception/object", self.on_object, ObjectObservation)
        b.subscribe("wavegrasp/perception/mesh", self.on_mesh, ObjectMesh)
        b.subscribe("wavegrasp/predictor/prediction", self.on_prediction, MotionPrediction)
        b.subscribe("wavegrasp/planner/plan", self.on_plan, GraspPlan)
        b.subscribe("wavegrasp/gate/decision", self.on_decision, GateDecision)

    def publish_markers(self, *markers: object) -> None:
        """Each array carries the latest marker of every namespace: a viewer that seeks
        restores only a topic's latest message, and would show one kind of marker alone."""
        self.latest.update({m.ns: m for m in markers})
        self.bus.publish_cdr(MARKERS_KEY, mk.marker_array(list(self.latest.values())),
                             mk.MARKER_ARRAY)
        self.counters["marker arrays"] += 1

    def link_frames(self, names: list[str], q: np.ndarray) -> list[tuple[str, str, np.ndarray]]:
        """(base, link, T_base_link) of every link of the chain and the jaw at ``q``."""
        position = dict(zip(names, q, strict=True))
        try:
            q_arm = np.array([position[n] for n in self.arm.joint_names])
        except KeyError as exc:
            raise BadMessage(f"joint_states: no position of joint {exc}") from None
        T_links = self.arm.forward_all(q_arm)
        base = self.arm.base_link
        frames = [(base, link, T) for link, T in zip(self.arm.link_names, T_links, strict=True)]
        at = dict(zip(self.arm.link_names, T_links, strict=True)) | {base: np.eye(4)}
        for joint in self.arm.jaw:
            if joint.parent in at:
                move = np.eye(4)
                move[:3, 3] = joint.axis * position.get(joint.name, 0.0)
                frames.append((base, joint.child, at[joint.parent] @ joint.origin @ move))
        return frames

    def on_joint_state(self, d: Delivery) -> None:
        try:
            stamp_ns, names, q, _qd = decode_joint_state(d.payload)
        except ValueError as exc:
            raise BadMessage(f"{d.key}: {exc}") from None
        self.bus.publish_cdr(TF_KEY, mk.transforms(stamp_ns, self.link_frames(names, q)),
                             mk.TF_MESSAGE, log_time_ns=stamp_ns)

    def on_object(self, msg: ObjectObservation, _d: Delivery) -> None:
        if msg.centroid is None:
            return
        c = msg.centroid
        self.centroid = np.array([c.x, c.y, c.z])
        T = np.eye(4)
        T[:3, 3] = self.centroid
        if msg.axis is not None:
            T[:3, :3] = frame_along(np.array([msg.axis.x, msg.axis.y, msg.axis.z]))
        stamp_ns = msg.header.stamp_ns
        self.bus.publish_cdr(TF_KEY, mk.transforms(stamp_ns, [("world", "object", T)]),
                             mk.TF_MESSAGE, log_time_ns=stamp_ns)
        size = 2 * max(msg.sigma_m or 0.0, 0.005)
        self.publish_markers(mk.marker("centroid", mk.SPHERE, stamp_ns, "world", ORANGE,
                                       (size, size, size), T=T))

    def on_mesh(self, msg: ObjectMesh, _d: Delivery) -> None:
        vertices, triangles = decode_mesh(msg.model_dump())
        # On a topic of its own: its triangles are too many to send again with every marker.
        mesh = mk.marker("mesh", mk.TRIANGLE_LIST, msg.header.stamp_ns, "object", GREY,
                         (1.0, 1.0, 1.0), path=vertices[triangles])
        self.bus.publish_cdr(MESH_KEY, mk.marker_array([mesh]), mk.MARKER_ARRAY)

    def on_prediction(self, msg: MotionPrediction, _d: Delivery) -> None:
        if not msg.samples:
            return
        path = np.array([[s.x, s.y, s.z] for s in msg.samples])
        end = np.eye(4)
        end[:3, 3] = path[-1]
        sigma = 2 * max(msg.samples[-1].sigma, 0.002)
        stamp_ns = msg.header.stamp_ns
        self.publish_markers(
            mk.marker("prediction", mk.LINE_STRIP, stamp_ns, "world", BLUE, (0.005, 0, 0),
                      path=path),
            mk.marker("prediction sigma", mk.SPHERE, stamp_ns, "world", BLUE[:3] + (0.3,),
                      (sigma, sigma, sigma), T=end))

    def on_plan(self, msg: GraspPlan, _d: Delivery) -> None:
        grasp = pose_matrix(msg.grasp)
        arrows = [mk.marker("grasp", mk.ARROW, msg.header.stamp_ns, "world", GREEN,
                            (0.08, 0.01, 0.01), T=grasp)]
        if msg.cartesian_path:
            path = np.array([[s.x, s.y, s.z] for s in msg.cartesian_path])
            arrows.append(mk.marker("approach", mk.LINE_STRIP, msg.header.stamp_ns, "world",
                                    GREEN, (0.004, 0, 0), path=path))
        self.publish_markers(*arrows)

    def on_decision(self, msg: GateDecision, _d: Delivery) -> None:
        self.publish_latency(msg)
        if self.centroid is None:
            return
        T = np.eye(4)
        T[:3, 3] = self.centroid + [0.0, 0.0, 0.15]
        error = (f"{msg.mean_error_m * 1e3:.1f} mm" if msg.mean_error_m is not None else "-")
        text = (f"GO  error {error} <= {msg.threshold_m * 1e3:.0f} mm" if msg.go else
                f"NO-GO  {msg.reason[:60]}")
        self.publish_markers(mk.marker("gate", mk.TEXT, msg.header.stamp_ns, "world",
                                       GREEN if msg.go else RED, (0, 0, 0.04), T=T, text=text))

    def publish_latency(self, msg: GateDecision) -> None:
        """The decision's milliseconds per hop (:class:`DecisionLatency`), from its trace."""
        trace = msg.header.trace
        try:
            hops = dict(hop_times_ms(trace))
        except ValueError as exc:
            raise BadMessage(f"wavegrasp/gate/decision header.trace: {exc}") from None
        self.latencies += 1
        self.bus.publish(LATENCY_KEY, DecisionLatency(
            header=new_header("scene", self.latencies, msg.header.stamp_ns),
            plan_id=msg.plan_id, go=msg.go, hops_ms=hops,
            total_ms=(trace[-1].sent_ns - trace[0].recv_ns) / 1e6))

    def on_tick(self) -> None:
        now = time.monotonic()
        if now - self._described_at >= self.cfg.description_period_s:
            self._described_at = now
            self.bus.publish_cdr(DESCRIPTION_KEY, self.description, mk.STRING)


def main(argv: list[str] | None = None) -> int:
    return service_main("scene", __doc__, SceneSettings, SceneService, argv)

"""Message contracts shared by every service: pydantic v2 models and the key tables.

``MESSAGE_TYPES`` maps a schema name (sent as the zenoh encoding's schema) to its model;
``KEY_TYPES`` maps each fixed key to the model it carries; ``ROS_KEYS`` maps the keys that
travel as CDR (ROS topics by the zenoh-bridge-ros2dds mapping: topic ``/a/b`` on key ``a/b``;
and perception's object points) to their ROS 2 type; ``SCENE_KEYS`` the same for the scene's
keys (what Foxglove and rviz2 draw).
"""

from __future__ import annotations

from pydantic import BaseModel

from wavegrasp.schemas.messages import (
    ArmStandby,
    ArmState,
    CartesianSample,
    Clock,
    DecisionLatency,
    FrameAck,
    GateAbort,
    GateDecision,
    GraspOutcome,
    GraspPlan,
    Header,
    Heartbeat,
    Hop,
    JointSample,
    MotionPrediction,
    ObjectMesh,
    ObjectObservation,
    PlayerStatus,
    Pose,
    PredictionSample,
    Quaternion,
    ServiceStats,
    Vec3,
)

MESSAGE_TYPES: dict[str, type[BaseModel]] = {
    m.__name__: m
    for m in (
        ObjectObservation,
        ObjectMesh,
        MotionPrediction,
        GraspPlan,
        ArmStandby,
        GateDecision,
        GateAbort,
        DecisionLatency,
        GraspOutcome,
        ArmState,
        Clock,
        FrameAck,
        Heartbeat,
        PlayerStatus,
        ServiceStats,
    )
}

CLOCK_KEY = "wavegrasp/clock"
HEARTBEAT_KEY = "wavegrasp/gate/heartbeat"

KEY_TYPES: dict[str, type[BaseModel]] = {
    CLOCK_KEY: Clock,
    "wavegrasp/perception/object": ObjectObservation,
    "wavegrasp/perception/mesh": ObjectMesh,
    "wavegrasp/predictor/prediction": MotionPrediction,
    "wavegrasp/planner/plan": GraspPlan,
    "wavegrasp/planner/standby": ArmStandby,
    "wavegrasp/gate/decision": GateDecision,
    "wavegrasp/gate/abort": GateAbort,
    HEARTBEAT_KEY: Heartbeat,
    "wavegrasp/sim/arm_state": ArmState,
    "wavegrasp/sim/outcome": GraspOutcome,
    "wavegrasp/player/status": PlayerStatus,
    "wavegrasp/scene/latency": DecisionLatency,
}

ROS_KEYS: dict[str, str] = {
    "trisect/points": "sensor_msgs/msg/PointCloud2",
    "tf_static": "tf2_msgs/msg/TFMessage",
    "groundtruth/object": "geometry_msgs/msg/PoseStamped",
    "wavegrasp/perception/points": "sensor_msgs/msg/PointCloud2",  # the object's, in world
    # The arm's, as ros2_control names them by default (runtime.settings.ArmTopics): a
    # bridge from a real arm's ROS 2 graph sends CDR without naming its type.
    "clock": "rosgraph_msgs/msg/Clock",  # the player's ticks, for nodes with use_sim_time
    "joint_states": "sensor_msgs/msg/JointState",
    "arm/joint_trajectory_controller/joint_trajectory": "trajectory_msgs/msg/JointTrajectory",
    "jaw/joint_trajectory_controller/joint_trajectory": "trajectory_msgs/msg/JointTrajectory",
}


# The scene's keys (services/scene), in the ROS 2 types Foxglove's 3D panel and rviz2 draw.
TF_KEY = "tf"
DESCRIPTION_KEY = "robot_description"
MARKERS_KEY = "wavegrasp/scene/markers"
MESH_KEY = "wavegrasp/scene/mesh"
SCENE_KEYS: dict[str, str] = {
    TF_KEY: "tf2_msgs/msg/TFMessage",
    DESCRIPTION_KEY: "std_msgs/msg/String",
    MARKERS_KEY: "visualization_msgs/msg/MarkerArray",
    MESH_KEY: "visualization_msgs/msg/MarkerArray",
}


def ack_key(service: str) -> str:
    """Key on which ``service`` acknowledges finished camera frames (:class:`FrameAck`)."""
    return f"wavegrasp/{service}/ack"


def stats_key(service: str) -> str:
    """Key on which ``service`` publishes its counters (:class:`ServiceStats`)."""
    return f"wavegrasp/{service}/stats"


def health_key(service: str) -> str:
    """Liveliness token key held by a running ``service``."""
    return f"wavegrasp/health/{service}"


def instance_key(service: str, instance: str) -> str:
    """Liveliness token key held by one process of ``service`` (``instance``: its session's
    id) beside :func:`health_key`: a router passes on one token per key, so a restarted
    service's own token shows while its dead predecessor's still lingers."""
    return f"{health_key(service)}/{instance}"


def model_for_key(key: str) -> type[BaseModel] | None:
    """The model a ``wavegrasp/...`` key carries, or None if the key is not in the contract."""
    if key in KEY_TYPES:
        return KEY_TYPES[key]
    parts = key.split("/")
    if len(parts) == 3 and parts[0] == "wavegrasp":
        return {"ack": FrameAck, "stats": ServiceStats}.get(parts[2])
    return None


__all__ = [
    "ArmState", "CartesianSample", "CLOCK_KEY", "Clock", "DecisionLatency", "FrameAck",
    "GateAbort", "GateDecision",
    "GraspOutcome", "ArmStandby", "GraspPlan", "Header", "Heartbeat", "HEARTBEAT_KEY", "Hop",
    "JointSample", "KEY_TYPES",
    "MESSAGE_TYPES", "MotionPrediction", "ObjectMesh", "ObjectObservation", "PlayerStatus", "Pose",
    "PredictionSample", "Quaternion", "ROS_KEYS", "SCENE_KEYS", "ServiceStats", "Vec3", "ack_key",
    "health_key", "instance_key", "model_for_key", "stats_key", "DESCRIPTION_KEY", "MARKERS_KEY",
    "MESH_KEY", "TF_KEY",
]

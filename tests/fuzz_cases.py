"""The fuzz test's inputs (``test_fuzz.py``): the bad-input cases, the ROS messages they are
built from, and a valid, richly filled example of each message type."""

from __future__ import annotations

import copy
import json
import math
import re
import time
import zlib
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from typing import Any

import numpy as np
from pydantic import BaseModel, ValidationError

from wavegrasp.recording_io.typestore import ros2_typestore
from wavegrasp.runtime.bus import CDR, JSON
from wavegrasp.runtime.trace import CdrAttachment
from wavegrasp.schemas import (
    MESSAGE_TYPES,
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
    ServiceStats,
    Vec3,
    model_for_key,
)
from wavegrasp.schemas.mesh_codec import encode_mesh
from wavegrasp.schemas.messages import INT64_MAX, MAX_COORDINATE_M
from wavegrasp.schemas.ros import msgtype as ros_msgtype
from wavegrasp.schemas.ros import to_cdr

SEED = 1729
HUGE_CLOUD = 2_000_001  # one point over the default WAVEGRASP_MAX_CLOUD_POINTS
CDR_HEADER = b"\x00\x01\x00\x00"  # little-endian CDR encapsulation


# --- cases --------------------------------------------------------------------------------

@dataclass(frozen=True)
class Case:
    """One payload for a key. ``reason``: a regex the bad reason must match (searched), or None
    for a valid message the service takes. ``recorded``: the recorder takes it all the same (it
    is well-formed CDR: the recorder keeps what went over the wire, its consumers judge it)."""

    kind: str
    payload: bytes
    encoding: str
    reason: str | None
    attachment: bytes | None = None
    recorded: bool = False

    def expect(self, service: str) -> str | None:
        return None if service == "recorder" and self.recorded else self.reason


def rng_for(*names: str) -> np.random.Generator:
    return np.random.default_rng([SEED, *(zlib.crc32(n.encode()) for n in names)])


def json_case(kind: str, obj: Any, schema: str, reason: str | None) -> Case:
    return Case(kind, json.dumps(obj).encode(), f"{JSON};{schema}", reason)


def message_case(kind: str, msg: BaseModel, reason: str | None = None) -> Case:
    """``msg`` as the services send it: CDR of its ``wavegrasp_msgs`` type."""
    return Case(kind, to_cdr(msg), f"{CDR};{ros_msgtype(type(msg).__name__)}", reason)


def json_message_case(kind: str, msg: BaseModel, reason: str | None = None) -> Case:
    """``msg`` as JSON of its model (what a tool may publish)."""
    return Case(kind, msg.model_dump_json().encode(), f"{JSON};{type(msg).__name__}", reason)


def leaves(obj: Any, path: tuple = ()) -> Iterator[tuple[tuple, Any]]:
    """(path, value) of every scalar in a JSON tree."""
    if isinstance(obj, dict):
        for k, v in obj.items():
            yield from leaves(v, (*path, k))
    elif isinstance(obj, list):
        for i, v in enumerate(obj):
            yield from leaves(v, (*path, i))
    else:
        yield path, obj


def replaced(obj: Any, path: tuple, value: Any) -> Any:
    out = copy.deepcopy(obj)
    node = out
    for p in path[:-1]:
        node = node[p]
    node[path[-1]] = value
    return out


def removed(obj: Any, path: tuple) -> Any:
    out = copy.deepcopy(obj)
    node = out
    for p in path[:-1]:
        node = node[p]
    del node[path[-1]]
    return out


def dotted(path: tuple) -> str:
    return ".".join(str(p) for p in path)


def json_cases(key: str, example: BaseModel, rng: np.random.Generator) -> list[Case]:
    """Every kind of malformed JSON for ``key``, from a valid ``example`` of its model (on a
    key outside the contract, of the type the encoding names)."""
    model = type(example)
    contract = model_for_key(key) is not None
    name = model.__name__
    at = f"^{re.escape(key)}: {name}\\."
    valid = example.model_dump(mode="json")
    cases = [Case(f"random bytes ({n})", b"\x00" + rng.bytes(n), f"{JSON};{name}",
                  at + r"payload: Invalid JSON") for n in (7, 300)]
    cases.append(Case("empty payload", b"", f"{JSON};{name}", at + r"payload: Invalid JSON"))
    cases.append(Case("truncated JSON", json.dumps(valid).encode()[:-9], f"{JSON};{name}",
                      at + r"payload: Invalid JSON"))
    cases.append(Case("binary encoding", json.dumps(valid).encode(), "application/octet-stream",
                      r"encoding 'application/octet-stream', expected application/cdr or "
                      r"application/json" if contract else r"no message type known for this key"))
    for kind, obj in (("a list", [1, 2]), ("a number", 42), ("a string", "text"),
                      ("null", None), ("a bool", True)):
        cases.append(json_case(f"JSON {kind}", obj, name, at + r"payload: Input should be an "
                               r"object|" + at + r"payload: Input should be a valid dictionary"))
    other = FrameAck if model is not FrameAck else Clock
    if contract:  # elsewhere any type may come
        cases.append(json_message_case(
            f"another type's JSON ({other.__name__})", EXAMPLES[other](),
            f"encoding names schema {other.__name__}, expected {name}"))
        cases.append(message_case(
            f"another type's CDR ({other.__name__})", EXAMPLES[other](),
            f"encoding names schema {re.escape(ros_msgtype(other.__name__))}, expected "
            f"{re.escape(ros_msgtype(name))}"))
    cases.append(json_case("an empty object", {}, name, at + r"\w+: Field required"))
    for field, info in model.model_fields.items():
        if info.is_required() and field in valid:
            cases.append(json_case(f"missing {field}", removed(valid, (field,)), name,
                                   at + re.escape(field) + ": Field required"))
    cases += nested_missing(valid, model, at)
    for field in [f for f, v in valid.items() if v is not None][:4]:
        wrong = "text" if not isinstance(valid[field], str) else {"wrong": 1}
        cases.append(json_case(f"{field} of the wrong type", replaced(valid, (field,), wrong),
                               name, at + re.escape(field) + r"\b"))
    cases += number_cases(valid, name, at)
    return cases


def nested_missing(valid: dict, model: type[BaseModel], at: str) -> list[Case]:
    """Nested required fields removed (two at most): e.g. ``samples.0.t_ns``."""
    cases = []
    for path, _ in leaves(valid):
        if len(path) < 2 or len(cases) == 2:
            continue
        try:
            model.model_validate(removed(valid, path))
        except ValidationError as exc:
            if exc.errors()[0]["type"] == "missing":
                cases.append(json_case(f"missing {dotted(path)}", removed(valid, path),
                                       model.__name__, at + re.escape(dotted(path))
                                       + ": Field required"))
    return cases


def number_cases(valid: dict, name: str, at: str) -> list[Case]:
    """NaN, inf and too-big numbers in float fields, ints beyond int64 or negative times and
    counts, coordinates beyond MAX_COORDINATE_M."""
    cases = []
    floats = [p for p, v in leaves(valid) if isinstance(v, float)][:3]
    for path in floats:
        for token in ("NaN", "Infinity", "-Infinity", "1e400"):
            text = json.dumps(replaced(valid, path, "@@")).replace('"@@"', token)
            cases.append(Case(f"{token} in {dotted(path)}", text.encode(), f"{JSON};{name}",
                              at + re.escape(dotted(path)) + r"(\.\w+)*: Input should be a "
                              "finite number"))
    ints = [p for p, v in leaves(valid) if isinstance(v, int) and not isinstance(v, bool)]
    ints = sorted(ints, key=lambda p: p[0] == "header")[:3]
    for path in ints:
        cases.append(json_case(f"10**30 in {dotted(path)}", replaced(valid, path, 10**30), name,
                               at + re.escape(dotted(path)) + ": Input should be less than or "
                               f"equal to {INT64_MAX}"))
        cases.append(json_case(f"-1 in {dotted(path)}", replaced(valid, path, -1), name,
                               at + re.escape(dotted(path)) + ": Input should be greater than "
                               "or equal to 0"))
    coords = [p for p, v in leaves(valid) if p and p[-1] in ("x", "y", "z")
              and "orientation" not in p][:2]
    for path in coords:
        cases.append(json_case(f"1e300 in {dotted(path)}", replaced(valid, path, 1e300), name,
                               at + re.escape(dotted(path)) + ": Input should be less than or "
                               f"equal to {MAX_COORDINATE_M:g}"))
    return cases


def cdr_cases(key: str, msgtype: str, valid: bytes, rng: np.random.Generator) -> list[Case]:
    """Structurally malformed CDR for ``key``: nobody can read it, the recorder included."""
    enc = f"{CDR};{msgtype}"
    bad = f"not a valid {re.escape(msgtype)}"
    cases = [Case(f"random bytes ({n})", rng.bytes(n), enc, bad) for n in (3, 64, 4000)]
    cases += [Case(f"random body ({n})", CDR_HEADER + rng.bytes(n), enc, bad) for n in (16, 500)]
    cases.append(Case("empty payload", b"", enc, bad))
    cases += [Case(f"truncated to {n} bytes", valid[:n], enc, bad)  # short of the whole
              for n in sorted({min(12, len(valid) - 1), len(valid) // 2, len(valid) - 1})]
    cases.append(Case("JSON on a CDR key", b'{"header": {}}', JSON,
                      f"{bad}|{re.escape(key)}: no message type known"))
    return cases


def own_cdr_cases(key: str, example: BaseModel, rng: np.random.Generator) -> list[Case]:
    """Malformed CDR of one of our messages (``example``'s type): garbage and truncations
    (:func:`cdr_cases`), and well-formed CDR whose values the model refuses: a negative
    sequence number, a NaN where a float must be finite."""
    model, name = type(example), type(example).__name__
    msgtype = ros_msgtype(name)
    at = f"^{re.escape(key)}: {name}\\."
    valid = to_cdr(example)
    cases = [c for c in cdr_cases(key, msgtype, valid, rng) if c.encoding != JSON]
    ros = store().deserialize_cdr(valid, msgtype)
    ros.trace.seq = -1
    cases.append(Case("a negative seq", bytes(store().serialize_cdr(ros, msgtype)),
                      f"{CDR};{msgtype}", at + r"header\.seq: Input should be greater than"))
    floats = [f for f, info in model.model_fields.items()
              if info.annotation is float and isinstance(getattr(example, f), float)]
    if floats:
        ros = store().deserialize_cdr(valid, msgtype)
        setattr(ros, floats[0], math.nan)
        cases.append(Case(f"NaN in {floats[0]}", bytes(store().serialize_cdr(ros, msgtype)),
                          f"{CDR};{msgtype}", at + re.escape(floats[0]) + r": Input should be "
                          r"a finite number"))
    return cases


# --- ROS messages --------------------------------------------------------------------------

store = ros2_typestore


def ros_time(stamp_ns: int) -> Any:
    return store().types["builtin_interfaces/msg/Time"](sec=stamp_ns // 10**9,
                                                          nanosec=stamp_ns % 10**9)


def cloud_cdr(points: np.ndarray, stamp_ns: int, *, fields: str = "xyz", datatype: int = 7,
              offsets: list[int] | None = None, step: int | None = None,
              data: bytes | None = None) -> bytes:
    """A PointCloud2 in the camera frame; the keyword arguments spoil its layout."""
    t = store().types
    size = {7: 4, 5: 4, 2: 1}[datatype]
    offsets = offsets if offsets is not None else [size * i for i in range(len(fields))]
    step = step if step is not None else size * len(fields)
    raw = data if data is not None else np.ascontiguousarray(points, dtype="<f4").tobytes()
    msg = t["sensor_msgs/msg/PointCloud2"](
        header=t["std_msgs/msg/Header"](stamp=ros_time(stamp_ns), frame_id="trisect_optical"),
        height=1, width=len(points),
        fields=[t["sensor_msgs/msg/PointField"](name=n, offset=o, datatype=datatype, count=1)
                for n, o in zip(fields, offsets, strict=True)],
        is_bigendian=False, point_step=step, row_step=step * len(points),
        data=np.frombuffer(raw, dtype=np.uint8), is_dense=False)
    return bytes(store().serialize_cdr(msg, "sensor_msgs/msg/PointCloud2"))


def tf_cdr(transforms: list[tuple[str, str, tuple, tuple]], stamp_ns: int = 0) -> bytes:
    """A TFMessage of (parent, child, translation xyz, rotation xyzw)."""
    t = store().types
    msgs = [t["geometry_msgs/msg/TransformStamped"](
        header=t["std_msgs/msg/Header"](stamp=ros_time(stamp_ns), frame_id=parent),
        child_frame_id=child,
        transform=t["geometry_msgs/msg/Transform"](
            translation=t["geometry_msgs/msg/Vector3"](x=p[0], y=p[1], z=p[2]),
            rotation=t["geometry_msgs/msg/Quaternion"](x=q[0], y=q[1], z=q[2], w=q[3])))
        for parent, child, p, q in transforms]
    return bytes(store().serialize_cdr(t["tf2_msgs/msg/TFMessage"](transforms=msgs),
                                       "tf2_msgs/msg/TFMessage"))


def pose_cdr(stamp_ns: int, p: tuple, q: tuple = (0.0, 0.0, 0.0, 1.0)) -> bytes:
    t = store().types
    msg = t["geometry_msgs/msg/PoseStamped"](
        header=t["std_msgs/msg/Header"](stamp=ros_time(stamp_ns), frame_id="world"),
        pose=t["geometry_msgs/msg/Pose"](
            position=t["geometry_msgs/msg/Point"](x=p[0], y=p[1], z=p[2]),
            orientation=t["geometry_msgs/msg/Quaternion"](x=q[0], y=q[1], z=q[2], w=q[3])))
    return bytes(store().serialize_cdr(msg, "geometry_msgs/msg/PoseStamped"))


def attachment(seq: int, log_time_ns: int) -> bytes:
    return CdrAttachment(seq, time.time_ns(), bytes(16), log_time_ns).encode()


NAN_TF = [("world", "trisect_optical", (math.nan, 0, 0), (0, 0, 0, 1))]
TILTED_TF = [("world", "trisect_optical", (0, 0, 0), (0.5, 0, 0, 0.5))]
SELF_TF = [("world", "world", (0, 0, 0), (0, 0, 0, 1))]
BACK_TF = [("trisect_optical", "world", (0, 0, 0), (0, 0, 0, 1))]


def tf_semantic_cases() -> list[Case]:
    """Well-formed TFMessages no consumer can use (the recorder keeps them) and odd ones."""
    enc = f"{CDR};tf2_msgs/msg/TFMessage"
    return [Case("NaN translation", tf_cdr(NAN_TF), enc, r"transform has NaN or inf",
                 recorded=True),
            Case("non-unit quaternion", tf_cdr(TILTED_TF), enc, r"not a unit quaternion",
                 recorded=True),
            Case("a frame its own parent", tf_cdr(SELF_TF), enc,
                 r"transform world -> world would make a loop", recorded=True),
            Case("a loop back to world", tf_cdr(BACK_TF), enc,
                 r"transform trisect_optical -> world would make a loop", recorded=True),
            Case("no transforms", tf_cdr([]), enc, None)]


def pose_semantic_cases(stamp_ns: int) -> list[Case]:
    enc = f"{CDR};geometry_msgs/msg/PoseStamped"
    return [Case("NaN position", pose_cdr(stamp_ns, (math.nan, 0, 0)), enc,
                 r"transform has NaN or inf", recorded=True),
            Case("inf position", pose_cdr(stamp_ns, (0, math.inf, 0)), enc,
                 r"transform has NaN or inf", recorded=True),
            Case("zero quaternion", pose_cdr(stamp_ns, (0, 0, 0), (0, 0, 0, 0)), enc,
                 r"not a unit quaternion", recorded=True),
            Case("short attachment", pose_cdr(stamp_ns, (0, 0, 0)), enc,
                 r"attachment of 5 bytes", attachment=b"\x01" * 5),
            Case("negative seq in attachment", pose_cdr(stamp_ns, (0, 0, 0)), enc,
                 r"attachment seq is negative",
                 attachment=CdrAttachment(-3, 1, bytes(16), 1).encode())]


def cloud_semantic_cases(points: np.ndarray, stamp_ns: int) -> list[Case]:
    """Well-formed PointCloud2s perception cannot use (the recorder keeps them); the huge one
    (sent to perception only) is refused unread."""
    enc = f"{CDR};sensor_msgs/msg/PointCloud2"
    n = len(points)
    return [
        Case("x, y, z as int32", cloud_cdr(points.astype("<i4").view("<f4"), stamp_ns,
                                           datatype=5), enc,
             r"x, y, z must be float32 or float64", recorded=True),
        Case("no z field", cloud_cdr(points[:, :2], stamp_ns, fields="xy"), enc,
             r"PointCloud2 has no field z", recorded=True),
        Case("fields beyond point_step", cloud_cdr(points, stamp_ns, offsets=[0, 4, 8], step=8,
                                                   data=points[:, :2].astype("<f4").tobytes()),
             enc, r"end at byte 12 of a point, beyond its point_step 8", recorded=True),
        Case("data shorter than the points", cloud_cdr(points, stamp_ns,
                                                       data=points[: n // 2].astype(
                                                           "<f4").tobytes()), enc,
             rf"PointCloud2 data has {12 * (n // 2)} bytes", recorded=True),
        Case("short attachment", cloud_cdr(points, stamp_ns), enc, r"attachment of 5 bytes",
             attachment=b"\x01" * 5),
        Case("negative log time in attachment", cloud_cdr(points, stamp_ns), enc,
             r"attachment log_time_ns is negative",
             attachment=CdrAttachment(1, 1, bytes(16), -1).encode()),
    ]


def huge_cloud_case(stamp_ns: int) -> Case:
    pts = np.random.default_rng(SEED).uniform(-1, 1, (HUGE_CLOUD, 3)).astype("<f4")
    pts[:, 2] += 2.0  # in front of the camera: looking for the object in it takes ~20 s
    return Case(f"{HUGE_CLOUD} points", cloud_cdr(pts, stamp_ns),
                f"{CDR};sensor_msgs/msg/PointCloud2",
                rf"PointCloud2 of {HUGE_CLOUD}x1 = {HUGE_CLOUD} points, more than the limit "
                r"of 2000000")


# --- valid messages ------------------------------------------------------------------------

def header(stamp_ns: int, seq: int = 1) -> Header:
    return Header(seq=seq, stamp_ns=stamp_ns, trace=[Hop(service="source", recv_ns=time.time_ns(),
                                                         sent_ns=time.time_ns())])


def tetrahedron(size: float = 0.05) -> dict[str, str | int]:
    v = np.array([[1, 1, 1], [1, -1, -1], [-1, 1, -1], [-1, -1, 1]], dtype=float) * size
    return encode_mesh(v, np.array([[0, 1, 2], [0, 3, 1], [0, 2, 3], [1, 3, 2]]))


def example_plan(plan_id: str = "example", t0: int = 10**18, joints: int = 6) -> GraspPlan:
    names = [f"joint_{i}" for i in range(joints)]
    return GraspPlan(
        header=header(t0), plan_id=plan_id, t_start_ns=t0 + 10**8, t_grasp_ns=t0 + 10**9,
        grasp=Pose(position=Vec3(x=0.1, y=-0.2, z=0.5)), approach=Vec3(x=0, y=0, z=-1),
        joint_names=names,
        joint_trajectory=[JointSample(t_ns=t0 + k * 10**8, positions=[0.1 * k] * joints,
                                      velocities=[0.0] * joints) for k in range(2)],
        cartesian_path=[CartesianSample(t_ns=t0 + k * 10**8, x=0.1, y=0.2, z=0.3 + k * 0.01)
                        for k in range(2)],
        confidence=0.5, waypoints=[Vec3(x=0.1, y=0.2, z=0.3)], t_final_ns=t0 + 8 * 10**8,
        jaw_preshape_m=0.14, t_close_ns=t0 + 9 * 10**8,
        candidates=[Pose(position=Vec3(x=0.1, y=-0.2, z=0.5))])


#: A valid, richly filled message of each type: what the JSON cases spoil.
EXAMPLES: dict[type[BaseModel], Callable[[], BaseModel]] = {
    Clock: lambda: Clock(header=header(10**18), rate=1.0, published={"trisect/points": 3}),
    FrameAck: lambda: FrameAck(header=header(10**18), service="perception", frame_seq=3),
    Heartbeat: lambda: Heartbeat(header=header(10**18), period_s=0.1),
    ObjectObservation: lambda: ObjectObservation(
        header=header(10**18), centroid=Vec3(x=0.1, y=-0.2, z=0.5), points_used=400,
        quality=0.9, sigma_m=0.001, shape="sphere", axis=Vec3(x=0, y=0, z=1), radius_m=0.06,
        length_m=0.12, fit_rms_m=0.0005),
    ObjectMesh: lambda: ObjectMesh(header=header(10**18), shape="sphere", volume_m3=0.0006,
                                   frames=20, **tetrahedron()),
    MotionPrediction: lambda: MotionPrediction(
        header=header(10**18), model="blend", period_s=1.5, parameters={"omega": 4.2},
        samples=[PredictionSample(t_ns=10**18 + k * 10**8, x=0.1, y=-0.2, z=0.5 + 0.01 * k,
                                  sigma=0.002) for k in range(4)]),
    GraspPlan: example_plan,
    ArmStandby: lambda: ArmStandby(
        header=header(10**18), t_start_ns=10**18 + 10**8,
        joint_names=[f"joint_{i}" for i in range(6)],
        joint_trajectory=[JointSample(t_ns=10**18 + 10**8 * (k + 1), positions=[0.1 * k] * 6)
                          for k in range(3)], reason="example"),
    GateDecision: lambda: GateDecision(header=header(10**18), plan_id="p", go=False,
                                       mean_error_m=0.004, threshold_m=0.01, window_s=2.0,
                                       reason="warming up"),
    GateAbort: lambda: GateAbort(header=header(10**18), plan_id="p", reason="stale "
                                 "prediction: 0.70 s old", value=0.7, limit=0.5),
    DecisionLatency: lambda: DecisionLatency(header=header(10**18), plan_id="p", go=True,
                                             hops_ms={"perception": 12.5, "planner -> gate": 0.4},
                                             total_ms=30.1),
    GraspOutcome: lambda: GraspOutcome(header=header(10**18), plan_id="p", trial=0, attempt=1,
                                       success=False, failure="timing",
                                       evidence={"object_passed_s": 0.2, "arm": "late"}),
    ArmState: lambda: ArmState(header=header(10**18), joint_names=["a", "b"],
                               positions=[0.1, 0.2], velocities=[0.0, 0.0], jaw_opening_m=0.1),
    PlayerStatus: lambda: PlayerStatus(header=header(10**18), state="playing",
                                       recording="x.mcap", pace="fast", frames=3, messages=9),
    ServiceStats: lambda: ServiceStats(header=header(10**18), service="gate",
                                       received={"k": 3}, bad={"k": 1}, uptime_s=1.5),
}
assert set(EXAMPLES) == set(MESSAGE_TYPES.values()), "add an example of the new message type"


# --- the arm's ROS 2 messages -------------------------------------------------------------

JOINT_STATE_ENC = f"{CDR};sensor_msgs/msg/JointState"
TRAJECTORY_ENC = f"{CDR};trajectory_msgs/msg/JointTrajectory"


def joint_state_cdr(stamp_ns: int, names: list[str], positions: list[float],
                    velocities: list[float]) -> bytes:
    """A JointState as any driver may send it: sizes unchecked."""
    t = ros2_typestore().types
    msg = t["sensor_msgs/msg/JointState"](
        header=t["std_msgs/msg/Header"](stamp=t["builtin_interfaces/msg/Time"](
            sec=stamp_ns // 10**9, nanosec=stamp_ns % 10**9), frame_id=""),
        name=list(names), position=np.array(positions, dtype=float),
        velocity=np.array(velocities, dtype=float), effort=np.zeros(0))
    return bytes(ros2_typestore().serialize_cdr(msg, "sensor_msgs/msg/JointState"))


def trajectory_cdr(stamp_ns: int, names: list[str], points: list[tuple[float, list[float]]]
                   ) -> bytes:
    """A JointTrajectory of (seconds from its stamp, positions) points: sizes unchecked."""
    t = ros2_typestore().types
    pts = [t["trajectory_msgs/msg/JointTrajectoryPoint"](
        positions=np.array(q, dtype=float), velocities=np.zeros(0), accelerations=np.zeros(0),
        effort=np.zeros(0), time_from_start=t["builtin_interfaces/msg/Duration"](
            sec=int(s), nanosec=int(round((s - int(s)) * 1e9)))) for s, q in points]
    msg = t["trajectory_msgs/msg/JointTrajectory"](
        header=t["std_msgs/msg/Header"](stamp=t["builtin_interfaces/msg/Time"](
            sec=stamp_ns // 10**9, nanosec=stamp_ns % 10**9), frame_id=""),
        joint_names=list(names), points=pts)
    return bytes(ros2_typestore().serialize_cdr(msg, "trajectory_msgs/msg/JointTrajectory"))


def joint_state_semantic_cases(stamp_ns: int, names: list[str], q: list[float]) -> list[Case]:
    n = len(names)
    return [Case("fewer positions than names", joint_state_cdr(stamp_ns, names, q[:-1], [0.0] * n),
                 JOINT_STATE_ENC, r"\d+ names but \d+ positions", recorded=True),
            Case("NaN position", joint_state_cdr(stamp_ns, names, [math.nan, *q[1:]], []),
                 JOINT_STATE_ENC, r"not finite", recorded=True),
            Case("another arm's joints", joint_state_cdr(stamp_ns, [f"j{k}" for k in range(n)],
                                                         q, []),
                 JOINT_STATE_ENC, r"joint_states lacks joints", recorded=True)]


def trajectory_semantic_cases(stamp_ns: int, names: list[str], q: list[float]) -> list[Case]:
    return [Case("no points", trajectory_cdr(stamp_ns, names, []), TRAJECTORY_ENC,
                 r"no points", recorded=True),
            Case("times not increasing", trajectory_cdr(stamp_ns, names, [(0.5, q), (0.5, q)]),
                 TRAJECTORY_ENC, r"increase strictly", recorded=True),
            Case("a point short of a joint", trajectory_cdr(stamp_ns, names, [(0.0, q[:-1])]),
                 TRAJECTORY_ENC, r"point 0 has \d+ positions", recorded=True),
            Case("another arm's joints", trajectory_cdr(
                stamp_ns, [f"j{k}" for k in range(len(names))], [(0.0, q)]),
                TRAJECTORY_ENC, r"neither the arm's|not the arm's", recorded=True)]

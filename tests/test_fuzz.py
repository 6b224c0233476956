"""Every subscriber survives malformed input ("Reliability and security").

Each service class runs its own loop on a thread, over a real router and real zenoh sessions,
and a test session publishes to every key it subscribes (taken from ``bus.subscriptions``, so
a new subscription is fuzzed too; a wildcard gets a sample of concrete keys) every kind of bad
input, seeded: random bytes, valid JSON of the wrong type or of another message type, JSON
missing required fields, NaN / inf / numbers too big, and on CDR keys truncated messages, clouds
empty, huge, of NaN points or with a wrong field layout, broken transforms and attachments; then
valid messages with duplicate and out-of-order stamps. Each key's batch ends with a valid
message. Checked: every malformed payload is counted under its key and logged with a reason
naming the problem; each valid-but-odd one is counted the same way where taking it would corrupt
the service (an older or repeated camera frame, observation or prediction) and otherwise taken;
the loop lives on and the service still handles valid input correctly afterwards.
"""

from __future__ import annotations

import copy
import json
import logging
import math
import re
import threading
import time
import zlib
from collections.abc import Callable, Iterator
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import zenoh
from mcap.reader import make_reader
from pydantic import BaseModel, ValidationError

from wavegrasp.arm import ArmModel
from wavegrasp.checks import StampOrder
from wavegrasp.gate.main import GateService, GateSettings
from wavegrasp.perception.main import PerceptionService, PerceptionSettings
from wavegrasp.planner.main import PlannerService, PlannerSettings
from wavegrasp.player.main import Player, PlayerSettings
from wavegrasp.predictor.main import PredictorService, PredictorSettings
from wavegrasp.recorder.main import Recorder, RecorderSettings
from wavegrasp.recording_io.reader import open_recording
from wavegrasp.recording_io.ros_msgs import decode_points, decode_pose
from wavegrasp.recording_io.typestore import ros2_typestore
from wavegrasp.runtime.bus import CDR, JSON
from wavegrasp.runtime.service import Service
from wavegrasp.runtime.trace import CdrAttachment
from wavegrasp.schemas import (
    KEY_TYPES,
    MESSAGE_TYPES,
    ROS_KEYS,
    ArmState,
    CartesianSample,
    Clock,
    FrameAck,
    GateDecision,
    GraspOutcome,
    GraspPlan,
    Header,
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
from wavegrasp.sim.main import SimService, SimSettings

from conftest import ROOT, Router, stop, wait_until

SAMPLE = ROOT / "recordings" / "wave1-buoy-5s.mcap"
SEED = 1729
HUGE_CLOUD = 2_000_001  # one point over the default WAVEGRASP_MAX_CLOUD_POINTS
#: Concrete keys a wildcard subscription (the recorder's ``**``) is fuzzed on.
WILDCARD_SAMPLE = sorted({*KEY_TYPES, *ROS_KEYS, "wavegrasp/gate/ack",
                          "wavegrasp/planner/stats", "fuzz/unknown"})
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
                      r"encoding 'application/octet-stream', expected application/json" if
                      contract else r"no message type known for this key"))
    for kind, obj in (("a list", [1, 2]), ("a number", 42), ("a string", "text"),
                      ("null", None), ("a bool", True)):
        cases.append(json_case(f"JSON {kind}", obj, name, at + r"payload: Input should be an "
                               r"object|" + at + r"payload: Input should be a valid dictionary"))
    other = FrameAck if model is not FrameAck else Clock
    if contract:  # elsewhere any type may come
        cases.append(message_case(f"another type's JSON ({other.__name__})", EXAMPLES[other](),
                                  f"encoding names schema {other.__name__}, expected {name}"))
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
    cases += [Case(f"truncated to {n} bytes", valid[:n], enc, bad)
              for n in (12, len(valid) // 2, len(valid) - 1)]
    cases.append(Case("JSON on a CDR key", b'{"header": {}}', JSON,
                      f"{bad}|{re.escape(key)}: no message type known"))
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
    GateDecision: lambda: GateDecision(header=header(10**18), plan_id="p", go=False,
                                       mean_error_m=0.004, threshold_m=0.01, window_s=2.0,
                                       reason="warming up"),
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


class Sample:
    """The sample recording: its transforms, camera frames and ground truth."""

    def __init__(self) -> None:
        messages = list(open_recording(SAMPLE).messages())
        self.tf = next(m.cdr for m in messages if m.topic == "/tf_static")
        self.frames = [m for m in messages if m.topic == "/trisect/points"]
        truths = [m for m in messages if m.topic == "/groundtruth/object"]
        self.truth_cdr = [m.cdr for m in truths]
        poses = [decode_pose(m.cdr) for m in truths]
        self.truth_ns = np.array([s for _, _, s in poses])
        self.truth_xyz = np.array([T[:3, 3] for T, _, _ in poses])

    def truth_at(self, stamp_ns: int) -> np.ndarray:
        return self.truth_xyz[int(np.searchsorted(self.truth_ns, stamp_ns))]

    def camera_points(self, k: int) -> np.ndarray:
        return decode_points(self.frames[k].cdr).points

    def prediction(self, i0: int, warm: bool = True, seq: int = 1) -> MotionPrediction:
        """The true motion from truth sample ``i0`` on, 3 s, every 50 ms: a perfect forecast."""
        idx = range(i0, min(i0 + 300, len(self.truth_ns)), 5)
        return MotionPrediction(
            header=header(int(self.truth_ns[i0]), seq), model="truth", period_s=1.5, warm=warm,
            samples=[PredictionSample(t_ns=int(self.truth_ns[i]), x=self.truth_xyz[i][0],
                                      y=self.truth_xyz[i][1], z=self.truth_xyz[i][2],
                                      sigma=0.002) for i in idx])


@pytest.fixture(scope="module")
def sample() -> Sample:
    return Sample()


# --- the harness ---------------------------------------------------------------------------

class BadLog(logging.Handler):
    """The bus's "bad message" warnings: (service, key, reason)."""

    def __init__(self) -> None:
        super().__init__(logging.WARNING)
        self.records: list[tuple[str, str, str]] = []

    def emit(self, record: logging.LogRecord) -> None:
        if str(record.msg).startswith("%s: bad message on"):
            service, key, _n, reason = record.args
            self.records.append((service, key, reason))

    def reasons(self, service: str, key: str) -> list[str]:
        return [r for s, k, r in list(self.records) if s == service and k == key]


@pytest.fixture(scope="module")
def router() -> Iterator[Router]:
    r = Router()
    yield r
    stop(r.proc)


@pytest.fixture
def bad_log() -> Iterator[BadLog]:
    handler = BadLog()
    logger = logging.getLogger("wavegrasp.runtime.bus")
    logger.addHandler(handler)
    yield handler
    logger.removeHandler(handler)


class Harness:
    """A service on its own loop thread, and the test's session that feeds it."""

    def __init__(self, router: Router, service: Service, bad_log: BadLog) -> None:
        self.service = service
        self.fuzz = router.bus("fuzz")
        self.log = bad_log
        self.error: BaseException | None = None
        self.thread = threading.Thread(target=self._loop, name=service.name, daemon=True)
        self.collected: dict[str, list] = {}
        self.timings: dict[str, float] = {}
        self.accepted: dict[str, int] = {}  # key -> payloads the service took (no bad count)
        self.matrix: dict[str, dict[str, int]] = {}  # key -> kind of input -> payloads
        self.stopped = False

    def _loop(self) -> None:
        """What ``Service.run`` does, less the signal handlers (the main thread's)."""
        s = self.service
        try:
            s.bus.declare_alive()
            s.on_start()
            Service.serve(s)  # the player: its loop, without the playback
            s.drain()
            s.on_stop()
        except BaseException as exc:  # a dying loop is what this test is about
            self.error = exc
            raise

    def start(self) -> None:
        self.thread.start()
        assert not self.fuzz.wait_for_services([self.service.name], timeout_s=15)

    def stop(self) -> None:
        if self.stopped:
            return
        self.stopped = True
        self.service.stop()
        self.thread.join(20)
        self.fuzz.close()
        self.service.bus.close()

    def alive(self) -> None:
        assert self.error is None, f"{self.service.name} loop died: {self.error!r}"
        assert self.thread.is_alive(), f"{self.service.name} loop ended"

    # -- sending and receiving -------------------------------------------------------------
    def send(self, key: str, case: Case) -> None:
        self.fuzz.session.put(key, case.payload, encoding=zenoh.Encoding(case.encoding),
                              attachment=case.attachment,
                              congestion_control=zenoh.CongestionControl.BLOCK)

    def send_msg(self, key: str, msg: BaseModel) -> None:
        self.send(key, message_case("valid", msg))

    def routes(self, key: str) -> int:
        """How many of the service's subscriptions take ``key``."""
        ke = zenoh.KeyExpr(key)
        return sum(zenoh.KeyExpr(s).includes(ke) for s in self.service.bus.subscriptions)

    def deliver(self, key: str, cases: list[Case], timeout: float = 30.0) -> None:
        """Send ``cases`` on ``key``; wait until the service has begun the last of them (so it
        has finished every one before it: one loop handles them in order)."""
        bus, before, n = self.service.bus, self.service.bus.received[key], len(cases)
        n *= self.routes(key)
        for case in cases:
            self.send(key, case)
        assert wait_until(lambda: bus.received[key] >= before + n, timeout=timeout), (
            f"{self.service.name} took {bus.received[key] - before} of {n} samples on {key}")

    def collect(self, key: str, model: type[BaseModel]) -> list:
        got: list = []
        self.fuzz.subscribe(key, lambda m, d: got.append(m), model)
        self.collected[key] = got
        return got

    def wait_for(self, key: str, predicate: Callable[[Any], bool], timeout: float = 20.0):
        """The first message collected on ``key`` that satisfies ``predicate``."""
        got = self.collected[key]

        def found() -> Any:
            while not self.fuzz.inbox.empty():
                self.fuzz.dispatch(self.fuzz.inbox.get())
            return next((m for m in got if predicate(m)), None)

        assert wait_until(lambda: found() is not None, timeout=timeout), (key, got[-3:])
        return found()

    # -- fuzzing --------------------------------------------------------------------------
    def fuzz_key(self, key: str, cases: list[Case], sentinel: Case) -> None:
        """Send every case then ``sentinel`` (valid) on ``key``; check each one that is
        malformed was counted and logged under ``key`` with its reason, and nothing else was."""
        bus, name = self.service.bus, self.service.name
        bad_before, logged_before = bus.bad[key], len(self.log.reasons(name, key))
        started = time.monotonic()
        self.deliver(key, [*cases, sentinel])
        self.timings[key] = time.monotonic() - started
        expected = [(c.kind, c.expect(name)) for c in cases
                    if c.expect(name) is not None] * self.routes(key)
        got = self.log.reasons(name, key)[logged_before:]
        pairs = match(got, [pattern for _, pattern in expected])
        surprises = [r for i, r in enumerate(got) if i not in pairs]
        unmatched = [e for j, e in enumerate(expected) if j not in pairs.values()]
        assert not surprises and not unmatched, (
            f"{name} on {key}:\n  counted with a reason no case expects: {surprises}\n"
            f"  not counted, or with another reason: {unmatched}")
        assert bus.bad[key] - bad_before == len(expected)
        if expected:
            assert re.search(expected[-1][1], bus.last_bad_reason[key]), bus.last_bad_reason
        self.accepted[key] = sum(c.expect(name) is None for c in cases) + 1
        kinds = self.matrix.setdefault(key, {})
        for c in cases:
            group = c.kind.split(" (")[0] if c.expect(name) else f"taken: {c.kind}"
            kinds[group] = kinds.get(group, 0) + 1
        self.alive()


def match(reasons: list[str], patterns: list[str]) -> dict[int, int]:
    """Pair each reason with a pattern it matches, as many as can be (reasons of two routes
    interleave): reason index -> pattern index."""
    owner: dict[int, int] = {}  # pattern -> reason

    def place(i: int, seen: set[int]) -> bool:
        for j, pattern in enumerate(patterns):
            if j not in seen and re.search(pattern, reasons[i]):
                seen.add(j)
                if j not in owner or place(owner[j], seen):
                    owner[j] = i
                    return True
        return False

    for i in range(len(reasons)):
        place(i, set())
    return {i: j for j, i in owner.items()}


def concrete_keys(service: Service) -> list[str]:
    """The keys to fuzz: each subscription, a wildcard one as a sample of concrete keys."""
    keys: list[str] = []
    for sub in service.bus.subscriptions:
        if "*" in sub or "$" in sub:
            keys += [k for k in WILDCARD_SAMPLE if zenoh.KeyExpr(sub).includes(zenoh.KeyExpr(k))]
        else:
            keys.append(sub)
    return list(dict.fromkeys(keys))


# --- the services ----------------------------------------------------------------------------

class Scenario:
    """How one service is fed: valid traffic before and after the fuzz, a valid message per
    key to end each batch, and each key's well-formed but bad or odd messages."""

    name = ""

    def __init__(self, router: Router, sample: Sample, tmp_path: Path) -> None:
        self.env, self.sample, self.tmp_path = router.env, sample, tmp_path
        self.t_ns = int(sample.frames[0].log_time_ns)
        self.acks = 0

    def make(self) -> Service:
        raise NotImplementedError

    def before(self, h: Harness) -> None:
        """Valid traffic that gives the service state to protect."""

    def after(self, h: Harness) -> None:
        """Valid traffic after the fuzz, and checks that the service still does its job."""

    def valid(self, key: str) -> Case:
        """A valid message on ``key`` that does not disturb the checks after the fuzz."""
        if key == "wavegrasp/clock":
            return message_case("valid", Clock(header=header(self.t_ns), rate=0.0))
        if key.endswith("/ack"):
            self.acks += 1
            return message_case("valid", FrameAck(header=header(self.t_ns),
                                                  service=key.split("/")[1],
                                                  frame_seq=self.acks))
        raise AssertionError(f"{self.name}: no valid message for {key}: add one to the scenario")

    def cdr_basis(self, key: str) -> bytes:
        """A valid CDR message of ``key`` to truncate."""
        return self.valid(key).payload

    def semantic(self, key: str) -> list[Case]:
        """Well-formed messages of the key's type that are bad in what they say."""
        return tf_semantic_cases() if key == "tf_static" else []

    def odd(self, key: str) -> list[Case]:
        """Valid messages with duplicate or out-of-order stamps, and other odd ones."""
        if key == "wavegrasp/clock":  # the clock follows the player, a replay may restart
            return [message_case("duplicate tick", Clock(header=header(self.t_ns), rate=0.0)),
                    message_case("tick from before", Clock(header=header(self.t_ns - 10**9)))]
        if key.endswith("/ack"):  # acknowledging a frame again is harmless
            ack = FrameAck(header=header(self.t_ns), service=key.split("/")[1],
                           frame_seq=self.acks)
            return [message_case("duplicate ack", ack),
                    message_case("ack of an older frame",
                                 ack.model_copy(update={"frame_seq": max(0, self.acks - 1)}))]
        return []

    def cases(self, key: str) -> list[Case]:
        rng = rng_for(self.name, key)
        model = model_for_key(key)
        if key in ROS_KEYS:
            fuzz = cdr_cases(key, ROS_KEYS[key], self.cdr_basis(key), rng)
        else:  # a key outside the contract: what its sender's encoding names
            fuzz = json_cases(key, EXAMPLES[model or FrameAck](), rng)
        return [*fuzz, *self.semantic(key), *self.odd(key)]


class PerceptionScenario(Scenario):
    name = "perception"

    def make(self) -> Service:
        self.frame = 0  # the next camera frame of the sample to send
        return PerceptionService(PerceptionSettings.from_env("perception", env=self.env))

    def frame_case(self, k: int | None = None, kind: str = "valid") -> Case:
        """Camera frame ``k`` of the sample (the next one by default), as the player sends it."""
        if k is None:
            k, self.frame = self.frame, self.frame + 1
            self.t_ns = self.sample.frames[k].log_time_ns
        m = self.sample.frames[k]
        return Case(kind, m.cdr, f"{CDR};{m.msgtype}", None, attachment(k, m.log_time_ns))

    def tracked(self, h: Harness) -> None:
        """The newest frame's observation has a centroid within 5 mm of the truth."""
        obs = h.wait_for("wavegrasp/perception/object",
                         lambda o: o.header.stamp_ns == self.t_ns)
        assert obs.centroid is not None, obs.reason
        c = obs.centroid
        err = np.linalg.norm([c.x, c.y, c.z] - self.sample.truth_at(self.t_ns))
        assert err < 0.005, f"centroid {err * 1e3:.1f} mm from the truth"

    def before(self, h: Harness) -> None:
        self.observations = h.collect("wavegrasp/perception/object", ObjectObservation)
        h.deliver("tf_static", [self.valid("tf_static")])
        h.deliver("trisect/points", [self.frame_case() for _ in range(5)])
        self.tracked(h)

    def valid(self, key: str) -> Case:
        if key == "trisect/points":
            return self.frame_case()
        if key == "tf_static":
            return Case("valid", self.sample.tf, f"{CDR};tf2_msgs/msg/TFMessage", None)
        return super().valid(key)

    def cdr_basis(self, key: str) -> bytes:
        return self.sample.frames[0].cdr if key == "trisect/points" else super().cdr_basis(key)

    def semantic(self, key: str) -> list[Case]:
        if key != "trisect/points":
            return super().semantic(key)
        return [*cloud_semantic_cases(self.sample.camera_points(0), self.t_ns + 1),
                huge_cloud_case(self.t_ns + 2)]

    def odd(self, key: str) -> list[Case]:
        if key != "trisect/points":
            return super().odd(key)
        last, stamps = self.frame - 1, [m.log_time_ns for m in self.sample.frames]
        enc = f"{CDR};sensor_msgs/msg/PointCloud2"
        spotty = self.sample.camera_points(self.frame).copy()
        spotty[::5] = np.nan
        spotty[1::7] = np.inf
        self.frame += 1
        self.t_ns = stamps[self.frame - 1]
        return [
            replace(self.frame_case(last), kind="duplicate frame",
                    reason=rf"duplicate: stamp {stamps[last]} <= last {stamps[last]}"),
            replace(self.frame_case(last - 2), kind="older frame",
                    reason=rf"out of order: stamp {stamps[last - 2]} <= last {stamps[last]}"),
            Case("a third of the points NaN or inf", cloud_cdr(spotty, self.t_ns), enc, None),
            Case("no points", cloud_cdr(np.zeros((0, 3)), self.t_ns + 1), enc, None),
            Case("only NaN points", cloud_cdr(np.full((50, 3), np.nan), self.t_ns + 2), enc,
                 None),
        ]

    def after(self, h: Harness) -> None:
        h.deliver("trisect/points", [self.frame_case() for _ in range(3)])
        self.tracked(h)
        reasons = [o.reason for o in self.observations if o.reason]
        assert reasons.count("empty cloud") == 2, reasons  # no points; only NaN points
        # a refused frame is still reported, without a centroid: every frame is accounted for
        assert sum(r.startswith(("duplicate: stamp", "out of order: stamp")) for r in
                   reasons) == 2, reasons
        assert h.service.counters["nonfinite_points"] > 50
        assert h.timings["trisect/points"] < 10, "the huge cloud was processed, not refused"


class PredictorScenario(Scenario):
    name = "predictor"
    PERIOD_S = 1.5

    def make(self) -> Service:
        self.k = 0  # observations made
        return PredictorService(PredictorSettings.from_env("predictor", env=self.env))

    def motion(self, t_ns: int) -> np.ndarray:
        t = (t_ns - self.sample.frames[0].log_time_ns) * 1e-9
        w = 2 * math.pi / self.PERIOD_S
        return np.array([0.1 + 0.05 * math.sin(w * t), -0.3, 0.5 + 0.03 * math.sin(w * t + 1)])

    def observation(self, t_ns: int | None = None) -> ObjectObservation:
        if t_ns is None:
            self.k += 1
            self.t_ns = t_ns = self.sample.frames[0].log_time_ns + self.k * 10**8
        p = self.motion(t_ns)
        return ObjectObservation(header=header(t_ns, self.k),
                                 centroid=Vec3(x=p[0], y=p[1], z=p[2]), points_used=400,
                                 quality=1.0, sigma_m=0.001)

    def feed(self, h: Harness, n: int) -> MotionPrediction:
        h.deliver("wavegrasp/perception/object",
                  [message_case("valid", self.observation()) for _ in range(n)])
        return h.wait_for("wavegrasp/predictor/prediction",
                          lambda p: p.header.stamp_ns == self.t_ns)

    def before(self, h: Harness) -> None:
        self.predictions = h.collect("wavegrasp/predictor/prediction", MotionPrediction)
        self.feed(h, 40)

    def valid(self, key: str) -> Case:
        if key == "wavegrasp/perception/object":
            return message_case("valid", ObjectObservation(header=header(self.t_ns),
                                                           reason="object not found"))
        return super().valid(key)

    def odd(self, key: str) -> list[Case]:
        if key != "wavegrasp/perception/object":
            return super().odd(key)
        t = self.t_ns
        return [message_case("duplicate observation", self.observation(t),
                             rf"duplicate: stamp {t} <= last {t}"),
                message_case("older observation", self.observation(t - 2 * 10**8),
                             rf"out of order: stamp {t - 2 * 10**8} <= last {t}")]

    def after(self, h: Harness) -> None:
        fuzzed_until = self.t_ns
        self.feed(h, 10)
        assert h.service.model.updates == 50, "only the valid observations reach the model"
        fresh = [p for p in self.predictions if p.header.stamp_ns > fuzzed_until]
        assert len(fresh) == 10
        for pred in fresh:
            first = pred.samples[0]
            assert first.t_ns == pred.header.stamp_ns
            err = np.linalg.norm([first.x, first.y, first.z] - self.motion(first.t_ns))
            assert err < 0.01, f"prediction {err * 1e3:.1f} mm off at lead 0"


class PlannerScenario(Scenario):
    name = "planner"

    def make(self) -> Service:
        self.i = 0  # the truth sample the latest prediction starts at
        self.arm = ArmModel.load(None)
        return PlannerService(PlannerSettings.from_env("planner", env=self.env))

    def prediction(self, warm: bool = True) -> MotionPrediction:
        self.i += 5
        self.t_ns = int(self.sample.truth_ns[self.i])
        return self.sample.prediction(self.i, warm, seq=self.i)

    def arm_state(self) -> ArmState:
        n = len(self.arm.joint_names)
        return ArmState(header=header(self.t_ns), joint_names=list(self.arm.joint_names),
                        positions=self.arm.q_home.tolist(), velocities=[0.0] * n)

    def plan_once(self, h: Harness) -> GraspPlan:
        """With the arm at rest and no plan executing, a warm prediction gets its plan."""
        h.send_msg("wavegrasp/sim/outcome", GraspOutcome(header=header(self.t_ns), plan_id="x",
                                                         trial=0, attempt=1, success=False))
        h.send_msg("wavegrasp/sim/arm_state", self.arm_state())
        pred = self.prediction()
        h.send_msg("wavegrasp/clock", Clock(header=header(self.t_ns), rate=0.0))
        h.send_msg("wavegrasp/predictor/prediction", pred)
        return h.wait_for("wavegrasp/planner/plan", lambda p: p.header.stamp_ns == self.t_ns)

    def before(self, h: Harness) -> None:
        h.collect("wavegrasp/planner/plan", GraspPlan)
        h.deliver("tf_static", [self.valid("tf_static")])
        self.plan_once(h)

    def valid(self, key: str) -> Case:
        t = self.t_ns
        if key == "tf_static":
            return Case("valid", self.sample.tf, f"{CDR};tf2_msgs/msg/TFMessage", None)
        if key == "wavegrasp/perception/object":
            return message_case("valid", ObjectObservation(header=header(t), reason="no object"))
        if key == "wavegrasp/sim/arm_state":
            return message_case("valid", self.arm_state())
        if key == "wavegrasp/gate/decision":
            return message_case("valid", GateDecision(header=header(t), plan_id="x", go=False,
                                                      mean_error_m=None, threshold_m=0.01,
                                                      window_s=2.0))
        if key == "wavegrasp/sim/outcome":
            return message_case("valid", GraspOutcome(header=header(t), plan_id="x", trial=0,
                                                      attempt=1, success=False))
        if key == "wavegrasp/predictor/prediction":
            return message_case("valid", self.prediction(warm=False))
        return super().valid(key)

    def odd(self, key: str) -> list[Case]:
        t = self.t_ns
        if key == "wavegrasp/predictor/prediction":
            last = self.sample.prediction(self.i, seq=self.i)
            blip = last.model_copy(deep=True, update={"samples": last.samples[:3]})
            blip.header.stamp_ns = t + 1
            for k, s in enumerate(blip.samples):
                s.t_ns = t + 1 + k
            return [message_case("duplicate prediction", last,
                                 rf"duplicate: stamp {t} <= last {t}"),
                    message_case("older prediction", self.sample.prediction(self.i - 3),
                                 rf"out of order: stamp \d+ <= last {t}"),
                    message_case("prediction 2 ns long", blip)]  # no plan in it
        if key == "wavegrasp/sim/arm_state":
            state = self.arm_state()
            short = state.model_copy(update={"positions": state.positions[:-1]})
            other = state.model_copy(update={"joint_names": [
                f"j{k}" for k in range(len(state.joint_names))]})
            return [message_case("fewer positions than joints", short,
                                 r"arm_state has \d+ joint_names but \d+ positions"),
                    message_case("another arm's joints", other, r"arm_state lacks joints"),
                    message_case("duplicate arm state", state)]
        if key == "wavegrasp/gate/decision":
            go = GateDecision(header=header(t), plan_id="never-planned", go=True,
                              mean_error_m=0.001, threshold_m=0.01, window_s=2.0)
            return [message_case("go for a plan never made", go),
                    message_case("duplicate decision", go)]
        if key == "wavegrasp/sim/outcome":
            out = GraspOutcome(header=header(t - 10**9), plan_id="x", trial=0, attempt=1,
                               success=True)
            return [message_case("old outcome", out), message_case("duplicate outcome", out)]
        return super().odd(key)

    def after(self, h: Harness) -> None:
        n = h.service.counters["plans"]
        plan = self.plan_once(h)
        assert plan.t_grasp_ns > plan.t_start_ns > self.t_ns
        assert h.service.counters["plans"] == n + 1


class GateScenario(Scenario):
    name = "gate"
    PERIOD_S = 4.0
    T0 = 1_000 * 10**9

    def make(self) -> Service:
        self.last_s = 0.0
        return GateService(GateSettings.from_env("gate", env=self.env))

    def ns(self, t_s: float) -> int:
        return self.T0 + round(t_s * 1e9)

    def motion(self, t_s: float) -> np.ndarray:
        w = 2 * math.pi / self.PERIOD_S
        return np.array([0.6 + 0.05 * math.sin(w * t_s), 0.1,
                         -0.4 + 0.03 * math.sin(w * t_s + 1)])

    def observation(self, t_s: float) -> ObjectObservation:
        p = self.motion(t_s)
        return ObjectObservation(header=header(self.ns(t_s)),
                                 centroid=Vec3(x=p[0], y=p[1], z=p[2]), points_used=500,
                                 quality=1.0, sigma_m=0.001)

    def prediction(self, made_s: float) -> MotionPrediction:
        """The true motion from ``made_s`` to 1.5 s ahead."""
        samples = [PredictionSample(t_ns=self.ns(t), x=p[0], y=p[1], z=p[2], sigma=0.005)
                   for t in made_s + 0.05 * np.arange(31) for p in [self.motion(t)]]
        return MotionPrediction(header=header(self.ns(made_s)), model="test",
                                period_s=self.PERIOD_S, samples=samples)

    def plan(self, made_s: float, start_s: float, grasp_s: float, plan_id: str) -> GraspPlan:
        g = self.motion(grasp_s)
        return GraspPlan(header=header(self.ns(made_s)), plan_id=plan_id,
                         t_start_ns=self.ns(start_s), t_grasp_ns=self.ns(grasp_s),
                         grasp=Pose(position=Vec3(x=g[0], y=g[1], z=g[2])),
                         approach=Vec3(x=0, y=0, z=-1))

    def feed(self, h: Harness, start: int, end: int) -> None:
        """An observation and a prediction every 0.1 s, from ``start`` to ``end`` tenths."""
        for i in range(start, end + 1):
            h.send_msg("wavegrasp/perception/object", self.observation(i / 10))
            h.send_msg("wavegrasp/predictor/prediction", self.prediction(i / 10))
        self.last_s = end / 10

    def decide(self, h: Harness, plan: GraspPlan, now_s: float) -> GateDecision:
        self.t_ns = self.ns(now_s)
        h.send_msg("wavegrasp/clock", Clock(header=header(self.t_ns), rate=0.0))
        h.send_msg("wavegrasp/planner/plan", plan)
        return h.wait_for("wavegrasp/gate/decision", lambda d: d.plan_id == plan.plan_id)

    def before(self, h: Harness) -> None:
        self.tokens = [h.fuzz.session.liveliness().declare_token(f"wavegrasp/health/{s}")
                       for s in ("perception", "predictor", "planner")]
        assert wait_until(lambda: h.service.bus.alive_now() >= {
            "perception", "predictor", "planner"}, timeout=10)
        self.decisions = h.collect("wavegrasp/gate/decision", GateDecision)
        self.feed(h, 0, 30)
        d = self.decide(h, self.plan(3.0, 3.3, 4.0, "a"), now_s=3.05)
        assert d.go, d.reason
        h.send_msg("wavegrasp/sim/outcome", GraspOutcome(header=header(self.ns(3.05)),
                                                         plan_id="a", trial=0, attempt=1,
                                                         success=True))

    def valid(self, key: str) -> Case:
        t_s = self.last_s
        if key == "wavegrasp/perception/object":
            return message_case("valid", ObjectObservation(header=header(self.ns(t_s)),
                                                           reason="no object"))
        if key == "wavegrasp/predictor/prediction":
            return message_case("valid", self.prediction(t_s))
        if key == "wavegrasp/planner/plan":
            return message_case("valid", self.plan(0.0, 0.3, 1.0, "stale"))
        if key == "wavegrasp/sim/outcome":
            return message_case("valid", GraspOutcome(header=header(self.ns(t_s)),
                                                      plan_id="stale", trial=0, attempt=1,
                                                      success=False))
        return super().valid(key)

    def odd(self, key: str) -> list[Case]:
        t_s = self.last_s
        if key == "wavegrasp/perception/object":
            return [message_case("duplicate observation", self.observation(t_s),
                                 rf"duplicate: stamp {self.ns(t_s)} <= last {self.ns(t_s)}"),
                    message_case("older observation", self.observation(t_s - 0.5),
                                 rf"out of order: stamp {self.ns(t_s - 0.5)} <= last")]
        if key == "wavegrasp/predictor/prediction":  # kept in stamp order: they score alike
            return [message_case("duplicate prediction", self.prediction(t_s)),
                    message_case("older prediction", self.prediction(t_s - 1.0))]
        if key == "wavegrasp/planner/plan":  # each gets its no-go
            return [message_case("duplicate plan", self.plan(0.0, 0.3, 1.0, "stale")),
                    message_case("plan grasping before it starts",
                                 self.plan(t_s, t_s + 0.5, t_s + 0.3, "backwards"))]
        if key == "wavegrasp/sim/outcome":
            out = GraspOutcome(header=header(self.ns(1.0)), plan_id="a", trial=0, attempt=1,
                               success=True)
            return [message_case("old outcome", out), message_case("duplicate outcome", out)]
        return super().odd(key)

    def after(self, h: Harness) -> None:
        backwards = h.wait_for("wavegrasp/gate/decision", lambda d: d.plan_id == "backwards")
        assert not backwards.go and backwards.reason.startswith("bad plan"), backwards.reason
        self.feed(h, 31, 50)
        d = self.decide(h, self.plan(5.0, 5.3, 6.0, "b"), now_s=5.05)
        assert d.go, d.reason
        assert d.mean_error_m is not None and d.mean_error_m < 0.001
        for token in self.tokens:
            token.undeclare()


class SimScenario(Scenario):
    name = "sim"

    def make(self) -> Service:
        self.i = 100  # the latest truth sample sent
        self.t_ns = int(self.sample.truth_ns[self.i])
        return SimService(SimSettings.from_env("sim", env=self.env))

    def truth_case(self, i: int | None = None, kind: str = "valid") -> Case:
        """Ground truth sample ``i`` (10 samples on by default), as the player sends it."""
        if i is None:
            self.i += 10
            self.t_ns = int(self.sample.truth_ns[self.i])
            i = self.i
        return Case(kind, self.sample.truth_cdr[i], f"{CDR};geometry_msgs/msg/PoseStamped",
                    None, attachment(i, int(self.sample.truth_ns[i])))

    def frame(self, h: Harness) -> ArmState:
        """A ground truth then the frame's end: the scene moves there and the arm is reported."""
        h.deliver("groundtruth/object", [self.truth_case()])
        self.acks += 1
        h.send_msg("wavegrasp/gate/ack", FrameAck(header=header(self.t_ns), service="gate",
                                                  frame_seq=self.acks))
        return h.wait_for("wavegrasp/sim/arm_state",
                          lambda s: s.header.seq == self.acks)

    def before(self, h: Harness) -> None:
        h.collect("wavegrasp/sim/arm_state", ArmState)
        h.deliver("tf_static", [self.valid("tf_static")])
        p = self.sample.truth_xyz[self.i]
        h.send_msg("wavegrasp/perception/object", ObjectObservation(
            header=header(self.t_ns), centroid=Vec3(x=p[0], y=p[1], z=p[2]), shape="sphere",
            radius_m=0.06, length_m=0.12))
        self.frame(h)
        assert h.service.world is not None

    def valid(self, key: str) -> Case:
        t = self.t_ns
        if key == "tf_static":
            return Case("valid", self.sample.tf, f"{CDR};tf2_msgs/msg/TFMessage", None)
        if key == "groundtruth/object":
            return self.truth_case()
        if key == "wavegrasp/perception/object":
            return message_case("valid", ObjectObservation(header=header(t), reason="no object"))
        if key == "wavegrasp/perception/mesh":
            return message_case("valid", ObjectMesh(header=header(t), shape="sphere",
                                                    volume_m3=1e-3, frames=20,
                                                    **tetrahedron(0.06)))
        if key == "wavegrasp/predictor/prediction":
            return message_case("valid", self.sample.prediction(self.i, seq=self.i))
        if key == "wavegrasp/planner/plan":
            return message_case("valid", example_plan("stored", t))
        if key == "wavegrasp/gate/decision":
            return message_case("valid", GateDecision(header=header(t), plan_id="stored",
                                                      go=False, mean_error_m=None,
                                                      threshold_m=0.01, window_s=2.0))
        return super().valid(key)

    def cdr_basis(self, key: str) -> bytes:
        if key == "groundtruth/object":
            return self.sample.truth_cdr[0]
        return super().cdr_basis(key)

    def semantic(self, key: str) -> list[Case]:
        if key == "groundtruth/object":
            return pose_semantic_cases(self.t_ns + 1)
        return super().semantic(key)

    def odd(self, key: str) -> list[Case]:
        t = self.t_ns
        if key == "groundtruth/object":  # the scene does not go back (checked after)
            return [self.truth_case(self.i, "duplicate pose"),
                    self.truth_case(self.i - 30, "older pose")]
        if key == "wavegrasp/gate/decision":
            go = GateDecision(header=header(t), plan_id="never-planned", go=True,
                              mean_error_m=0.001, threshold_m=0.01, window_s=2.0)
            return [message_case("go for a plan never made", go,
                                 r"decision for plan never-planned that never arrived"),
                    message_case("go for a plan for another arm",
                                 go.model_copy(update={"plan_id": "stored"}),
                                 r"plan stored: joint_names .* are not the arm's"),
                    message_case("go for a plan of 2 positions a sample",
                                 go.model_copy(update={"plan_id": "narrow"}),
                                 r"plan narrow: joint_trajectory sample 0 has 2 positions, "
                                 r"the arm 6 joints")]
        if key == "wavegrasp/perception/mesh":
            flat = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]], dtype=float) * 0.05
            return [message_case("mesh of 3 vertices", ObjectMesh(
                header=header(t), shape="sphere", volume_m3=0.0, frames=1,
                **encode_mesh(flat, np.array([[0, 1, 2]]))),
                r"mesh of 3 vertices: a closed mesh needs 4")]
        if key == "wavegrasp/planner/plan":
            narrow = example_plan("narrow", t, joints=2)
            narrow.joint_names = list(ArmModel.load(None).joint_names)
            return [message_case("duplicate plan", example_plan("stored", t)),
                    message_case("plan of 2 positions a sample", narrow)]
        return super().odd(key)

    def after(self, h: Harness) -> None:
        s = h.service
        assert s.world is not None
        assert s.world.time_s == pytest.approx(self.t_ns * 1e-9, abs=1e-3), "scene went back"
        self.frame(h)
        assert s.world.time_s == pytest.approx(self.t_ns * 1e-9, abs=1e-3)
        for kind, scale, corners in (("flat", 0.05, [[0, 0, 0], [1, 0, 0], [0, 1, 0],
                                                      [1, 1, 0]]),
                                     ("huge", 1e6, [[1, 1, 1], [1, -1, -1], [-1, 1, -1],
                                                    [-1, -1, 1]])):
            mesh = encode_mesh(np.array(corners, dtype=float) * scale,
                               np.array([[0, 1, 2], [0, 3, 1], [0, 2, 3], [1, 3, 2]]))
            h.send_msg("wavegrasp/perception/mesh", ObjectMesh(
                header=header(self.t_ns), shape="sphere", volume_m3=0.0, frames=1, **mesh))
            state = self.frame(h)  # the frame is still finished, whatever the mesh
            assert state.header.stamp_ns == pytest.approx(self.t_ns, abs=10**6), kind


class RecorderScenario(Scenario):
    name = "recorder"

    def make(self) -> Service:
        return Recorder(RecorderSettings.from_env("recorder", env=self.env,
                                                  out=self.tmp_path / "run"))

    def valid(self, key: str) -> Case:
        model = model_for_key(key)
        if model is not None:
            msg = EXAMPLES[model]()
            msg.header.stamp_ns = self.t_ns
            return message_case("valid", msg)
        if key == "tf_static":
            return Case("valid", self.sample.tf, f"{CDR};{ROS_KEYS[key]}", None)
        if key == "groundtruth/object":
            return Case("valid", self.sample.truth_cdr[0], f"{CDR};{ROS_KEYS[key]}", None,
                        attachment(0, int(self.sample.truth_ns[0])))
        if key in ROS_KEYS:  # camera frames, perception's object points
            m = self.sample.frames[0]
            return Case("valid", m.cdr, f"{CDR};{ROS_KEYS[key]}", None,
                        attachment(0, m.log_time_ns))
        return message_case("valid", EXAMPLES[FrameAck]())

    def semantic(self, key: str) -> list[Case]:
        if key in ("trisect/points", "wavegrasp/perception/points"):
            return cloud_semantic_cases(self.sample.camera_points(0), self.t_ns)
        if key == "groundtruth/object":
            return pose_semantic_cases(self.t_ns)
        if key == "fuzz/unknown":
            return [Case("JSON without a schema", b"{}", JSON,
                         r"^fuzz/unknown: no message type known for this key"),
                    Case("CDR without a type", CDR_HEADER + bytes(8), CDR,
                         r"^fuzz/unknown: CDR payload without a message type")]
        return super().semantic(key)

    def odd(self, key: str) -> list[Case]:  # what is well-formed is recorded, duplicates too
        return [replace(self.valid(key), kind="duplicate")]

    def after(self, h: Harness) -> None:
        h.stop()  # writes the MCAP's summary
        kept: dict[str, int] = {}
        with (self.tmp_path / "run" / "run.mcap").open("rb") as f:
            for schema, channel, message in make_reader(f).iter_messages():
                key = channel.topic.removeprefix("/")
                kept[key] = kept.get(key, 0) + 1
                if channel.message_encoding == "json":  # nothing malformed was written
                    MESSAGE_TYPES[schema.name].model_validate_json(message.data)
                else:
                    store().deserialize_cdr(message.data, schema.name)
        assert {k: kept.get(k, 0) for k in h.accepted} == h.accepted


class PlayerScenario(Scenario):
    name = "player"

    def make(self) -> Service:
        return Player(PlayerSettings.from_env("player", env=self.env,
                                              ack_services=["recorder"]),
                      open_recording(SAMPLE))

    def before(self, h: Harness) -> None:
        self.acks = 3
        h.send_msg("wavegrasp/recorder/ack", FrameAck(header=header(self.t_ns),
                                                      service="recorder", frame_seq=3))
        assert wait_until(lambda: h.service.acked_seq == 3, timeout=10)

    def odd(self, key: str) -> list[Case]:
        if key == "wavegrasp/recorder/ack":
            return [*super().odd(key), message_case("another service's ack", FrameAck(
                header=header(self.t_ns), service="gate", frame_seq=10**6))]
        return super().odd(key)

    def after(self, h: Harness) -> None:
        assert h.service.acked_seq == self.acks  # neither older nor foreign acks counted
        h.send_msg("wavegrasp/recorder/ack", FrameAck(header=header(self.t_ns),
                                                      service="recorder", frame_seq=40))
        assert wait_until(lambda: h.service.acked_seq == 40, timeout=10)


SCENARIOS = [PerceptionScenario, PredictorScenario, PlannerScenario, GateScenario,
             SimScenario, RecorderScenario, PlayerScenario]


@pytest.mark.parametrize("scenario", SCENARIOS, ids=[s.name for s in SCENARIOS])
def test_every_subscriber_survives_malformed_input(
        scenario: type[Scenario], router: Router, sample: Sample, bad_log: BadLog,
        tmp_path: Path) -> None:
    feed = scenario(router, sample, tmp_path)
    service = feed.make()
    h = Harness(router, service, bad_log)
    try:
        h.start()
        feed.before(h)
        keys = concrete_keys(service)
        assert keys, f"{service.name} subscribes nothing"
        for key in keys:
            cases = feed.cases(key)
            h.fuzz_key(key, cases, feed.valid(key))
        feed.after(h)
        if not h.stopped:
            h.alive()
        print(f"\n{service.name}: " + "; ".join(
            f"{key}: {sum(kinds.values())} ({', '.join(f'{k} {n}' for k, n in kinds.items())})"
            for key, kinds in h.matrix.items()))
    finally:
        h.stop()
    assert h.error is None, f"{service.name} loop died: {h.error!r}"


def test_stamp_order_refuses_repeats_and_the_past_but_takes_a_restart() -> None:
    order = StampOrder(restart_s=1.0)
    order.check(5 * 10**9)
    with pytest.raises(ValueError, match=r"^duplicate: stamp 5000000000 <= last 5000000000$"):
        order.check(5 * 10**9)
    with pytest.raises(ValueError, match=r"^out of order: stamp 4100000000 <= last 5000000000$"):
        order.check(4_100_000_000)
    order.check(4 * 10**9)  # a second back or more: the stream starts over
    assert order.last_ns == 4 * 10**9
    order.check(4 * 10**9 + 1)

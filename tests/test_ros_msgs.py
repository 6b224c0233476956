"""Our messages as ROS 2 interfaces: the .msg files match the models, every model round-trips
through CDR, and bad CDR is refused naming what is wrong."""

from __future__ import annotations

import re
from pathlib import Path

import pytest
from pydantic import BaseModel

from wavegrasp import schemas as m
from wavegrasp.runtime.bus import CDR, JSON, BadMessage, Delivery, decode_model
from wavegrasp.schemas import Header, Hop
from wavegrasp.schemas.export import MSG_DIR
from wavegrasp.schemas.ros import (
    definitions,
    from_cdr,
    msgtype,
    to_cdr,
    typestore,
)

HEADER = Header(seq=12, stamp_ns=1_700_000_001_250_000_000, frame_id="world",
                trace=[Hop(service="source", recv_ns=5, sent_ns=5),
                       Hop(service="perception", recv_ns=7, sent_ns=11)])


def samples() -> list[BaseModel]:
    """One of each message, every optional field set in one and unset in another."""
    v = m.Vec3(x=0.1, y=-0.2, z=0.3)
    full = m.ObjectObservation(header=HEADER, centroid=v, points_used=812, quality=0.9,
                             sigma_m=0.002, reason=None, shape="box", axis=v, radius_m=0.03,
                             length_m=0.12, axial_offset_m=-0.01, fit_rms_m=0.001, side=v,
                             side_width_m=0.05, breadth_m=0.07, seabed_normal=v,
                             seabed_offset_m=1.5)
    plan = m.GraspPlan(
        header=HEADER, plan_id="12-170", t_start_ns=10, t_grasp_ns=20,
        grasp=m.Pose(position=v, orientation=m.Quaternion(x=0.5, y=0.5, z=0.5, w=0.5)),
        approach=v, joint_names=["a", "b"],
        joint_trajectory=[m.JointSample(t_ns=10, positions=[0.1, 0.2], velocities=[0.0, 1.0]),
                          m.JointSample(t_ns=20, positions=[0.3, 0.4])],
        cartesian_path=[m.CartesianSample(t_ns=10, x=1.0, y=2.0, z=3.0)], confidence=0.8,
        waypoints=[v, v], t_final_ns=15, jaw_preshape_m=0.09, t_close_ns=18,
        candidates=[m.Pose(position=v)], standby=[0.0, 1.0], update_of="11-170",
        t_contact_ns=None)
    outcome = m.GraspOutcome(header=HEADER, plan_id="12-170", trial=1, attempt=2, success=False,
                           failure="timing", evidence={"error_m": 0.031, "why": "late",
                                                       "closed": True, "n": 3}, aborted=True)
    stats = m.ServiceStats(header=HEADER, service="gate", subscriptions=["a/b"],
                         received={"a/b": 3}, bad={"a/b": 1}, last_bad_reason={"a/b": "x"},
                         counters={"plans": 2}, uptime_s=1.5, cpu_s=0.25)
    prediction = m.MotionPrediction(
        header=HEADER, model="blend", period_s=2.5, parameters={"k": 0.5}, warm=False,
        samples=[m.PredictionSample(t_ns=t, x=0.1 * t, y=0.0, z=-1.0, sigma=0.01)
                 for t in range(1, 5)])
    decision = m.GateDecision(header=HEADER, plan_id="p", go=False, mean_error_m=None,
                            threshold_m=0.02, window_s=1.0, reason="no", failed=["error"],
                            matches=4, latency_s=0.03)
    arm = m.ArmState(header=HEADER, joint_names=["a"], positions=[0.5], executing_plan_id="p",
                   returning=True)
    return [full, m.ObjectObservation(header=Header()), plan, outcome, stats, prediction,
            decision, arm]


def test_msg_files_are_current() -> None:
    for name, text in definitions().items():
        path = MSG_DIR / f"{name}.msg"
        assert path.exists() and path.read_text() == text, (
            f"{path} is out of date: run python -m wavegrasp.schemas.export")
    assert {p.stem for p in MSG_DIR.glob("*.msg")} == set(definitions())
    package = (MSG_DIR.parent / "package.xml").read_text()
    assert "<name>wavegrasp_msgs</name>" in package


def test_every_message_has_a_ros_type() -> None:
    for name in m.MESSAGE_TYPES:
        assert msgtype(name) in typestore().fielddefs, name
    fields = typestore().fielddefs[msgtype("GateDecision")][1]
    assert [f[0] for f in fields[:2]] == ["header", "trace"]
    assert fields[0][1][1] == "std_msgs/msg/Header"  # where ROS tools look for the stamp


@pytest.mark.parametrize("msg", samples(), ids=lambda m: type(m).__name__)
def test_cdr_round_trip(msg: BaseModel) -> None:
    data = to_cdr(msg)
    assert data[:4] == b"\x00\x01\x00\x00"  # little-endian CDR
    back = from_cdr(data, type(msg))
    assert back == msg
    ros = typestore().deserialize_cdr(data, msgtype(type(msg).__name__))
    assert ros.header.stamp.sec == 1_700_000_001 and ros.header.stamp.nanosec == 250_000_000 \
        or msg.header.stamp_ns == 0


def every_example() -> list[BaseModel]:
    """The samples above, and the fuzz test's richly filled example of every message type."""
    from fuzz_cases import EXAMPLES

    return [*samples(), *(make() for make in EXAMPLES.values())]


def test_our_cdr_is_byte_for_byte_rosbags() -> None:
    """The hand-written codec (``schemas/cdr.py``) writes what rosbags' serializer writes, and
    reads what it reads, for every message type, optional fields set and unset."""
    examples = every_example()
    assert {type(x) for x in examples} >= set(m.MESSAGE_TYPES.values())
    for msg in examples:
        name = type(msg).__name__
        data = to_cdr(msg)
        store, msgtype_ = typestore(), msgtype(name)  # rosbags reads it, writes it back alike
        assert bytes(store.serialize_cdr(store.deserialize_cdr(data, msgtype_), msgtype_)) == data
        assert from_cdr(data, type(msg)) == msg, name
        for n in range(4, len(data)):  # every truncation: refused, never a wrong message
            with pytest.raises(ValueError):
                from_cdr(data[:n], type(msg))


def test_the_evidence_keeps_its_kinds() -> None:
    outcome = next(x for x in samples() if isinstance(x, m.GraspOutcome))
    back = from_cdr(to_cdr(outcome), m.GraspOutcome)
    assert back.evidence == {"error_m": 0.031, "why": "late", "closed": True, "n": 3.0}
    assert isinstance(back.evidence["closed"], bool) and isinstance(back.evidence["why"], str)


def delivery(payload: bytes, encoding: str) -> Delivery:
    return Delivery("wavegrasp/gate/decision", payload, encoding, None, 0, 0)


def test_bad_cdr_is_refused_naming_key_and_problem() -> None:
    decision = next(x for x in samples() if isinstance(x, m.GateDecision))
    good = to_cdr(decision)
    encoding = f"{CDR};{msgtype('GateDecision')}"
    assert decode_model(delivery(good, encoding), m.GateDecision) == decision
    with pytest.raises(BadMessage, match="wavegrasp/gate/decision: not a valid "
                       "wavegrasp_msgs/msg/GateDecision"):
        decode_model(delivery(good[:-9], encoding), m.GateDecision)
    with pytest.raises(BadMessage, match="names schema wavegrasp_msgs/msg/GateAbort"):
        decode_model(delivery(good, f"{CDR};{msgtype('GateAbort')}"), m.GateDecision)
    # Valid CDR whose values break the model's bounds: refused naming the field.
    bad = decision.model_copy(update={"matches": -1})
    with pytest.raises(BadMessage, match="GateDecision.matches"):
        decode_model(delivery(to_cdr(bad), encoding), m.GateDecision)
    # JSON (a tool's, or an older sender's) still reads.
    assert decode_model(delivery(decision.model_dump_json().encode(), JSON),
                        m.GateDecision) == decision


def test_a_value_entry_of_unknown_kind_is_refused() -> None:
    outcome = next(x for x in samples() if isinstance(x, m.GraspOutcome))
    store = typestore()
    ros = store.deserialize_cdr(to_cdr(outcome), msgtype("GraspOutcome"))
    ros.evidence[0].kind = 7
    data = bytes(store.serialize_cdr(ros, msgtype("GraspOutcome")))
    with pytest.raises(ValueError, match="kind 7"):
        from_cdr(data, m.GraspOutcome)


def test_colcon_package_lists_the_standard_dependencies() -> None:
    text = (Path(MSG_DIR.parent) / "CMakeLists.txt").read_text()
    used = {line.split("/")[0] for t in definitions().values() for line in t.splitlines()
            if "/" in line.split(" ")[0] and not line.startswith("#")}
    for package in used:
        assert f"find_package({package} REQUIRED)" in text, package


def test_names_follow_rosidl_rules() -> None:
    """What rosidl (colcon) refuses: type names not in CamelCase, field names not lower case
    with single underscores, constants not upper case."""
    field = re.compile(r"^(?!.*__)(?!.*_$)[a-z][a-z0-9_]*$")
    for name, text in definitions().items():
        assert re.fullmatch(r"[A-Z][A-Za-z0-9]*", name), name
        for line in text.splitlines():
            if not line or line.startswith("#"):
                continue
            _type, rest = line.split(" ", 1)
            if "=" in rest:
                assert re.fullmatch(r"[A-Z][A-Z0-9_]*", rest.split("=")[0]), (name, line)
            else:
                assert field.match(rest), (name, line)

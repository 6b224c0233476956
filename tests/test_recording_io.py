"""Tests of wavegrasp.recording_io: MCAP writer/reader, bag conversions, errors."""

from __future__ import annotations

from collections import defaultdict
from pathlib import Path

import numpy as np
import pytest
from mcap.writer import Writer

from wavegrasp.recording_io.reader import (
    CONTRACT_TOPICS,
    RecordedMessage,
    RecordingError,
    open_recording,
)
from wavegrasp.recording_io.typestore import ros2_typestore
from wavegrasp.recording_io.writer import RecordingWriter, write_ros1_bag, write_ros2_bag

from conftest import make_recording

SECONDS = 2.0


@pytest.fixture(scope="module")
def tank(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return make_recording(tmp_path_factory.mktemp("rec") / "tank.mcap", SECONDS, seed=7)


@pytest.fixture(scope="module")
def messages(tank: Path) -> list[RecordedMessage]:
    return list(open_recording(tank).messages())


def by_topic(msgs: list[RecordedMessage]) -> dict[str, list[tuple[int, str, bytes]]]:
    out: dict[str, list[tuple[int, str, bytes]]] = defaultdict(list)
    for m in msgs:
        out[m.topic].append((m.log_time_ns, m.msgtype, m.cdr))
    return dict(out)


def test_synthetic_round_trip(tank: Path, messages: list[RecordedMessage]) -> None:
    rec = open_recording(tank)
    assert rec.format == "mcap"
    assert {"generator": "wavegrasp.wavetank", "seed": "7", "wave": "1",
            "object": "buoy"}.items() <= rec.metadata.items()
    assert rec.topics == {"/trisect/points": "sensor_msgs/msg/PointCloud2",
                          "/tf_static": "tf2_msgs/msg/TFMessage",
                          "/groundtruth/object": "geometry_msgs/msg/PoseStamped"}
    counts = {t: len(v) for t, v in by_topic(messages).items()}
    assert counts == {"/trisect/points": 20, "/tf_static": 2, "/groundtruth/object": 200}
    assert rec.message_count == len(messages) == 222
    times = [m.log_time_ns for m in messages]
    assert times == sorted(times) and (rec.start_ns, rec.end_ns) == (times[0], times[-1])
    assert "MSG: std_msgs/Header" in rec.msgdef("sensor_msgs/msg/PointCloud2")


def test_writer_bytes_and_determinism(tmp_path: Path, tank: Path) -> None:
    again = make_recording(tmp_path / "again.mcap", SECONDS, seed=7)
    assert again.read_bytes() == tank.read_bytes()
    other = make_recording(tmp_path / "other.mcap", SECONDS, seed=8)
    assert other.read_bytes() != tank.read_bytes()
    cdr = ros2_typestore().serialize_cdr(
        ros2_typestore().types["std_msgs/msg/String"](data="hi"), "std_msgs/msg/String")
    with RecordingWriter(tmp_path / "w.mcap", {"k": "v"}) as w:
        w.write_cdr("/chat", "std_msgs/msg/String", 5, cdr)
    rec = open_recording(tmp_path / "w.mcap", topics=None)
    assert [(m.topic, m.log_time_ns, m.cdr) for m in rec.messages()] == [("/chat", 5, cdr)]


@pytest.mark.parametrize("fmt", ["ros1", "ros2"])
def test_bag_conversions(tmp_path: Path, messages: list[RecordedMessage], fmt: str) -> None:
    if fmt == "ros1":
        path = write_ros1_bag(tmp_path / "x.bag", messages)
    else:
        path = write_ros2_bag(tmp_path / "x_bag", messages)
    rec = open_recording(path)
    assert (rec.format, rec.message_count, rec.metadata) == (fmt, len(messages), {})
    assert set(rec.topics) == set(CONTRACT_TOPICS)
    back = list(rec.messages())
    assert by_topic(back) == by_topic(messages)
    assert [m.log_time_ns for m in back] == sorted(m.log_time_ns for m in messages)
    assert "float64 x" in rec.msgdef("geometry_msgs/msg/PoseStamped")


def test_mixed_json_channels_are_skipped(tmp_path: Path, messages: list[RecordedMessage]) -> None:
    path = tmp_path / "run.mcap"
    with RecordingWriter(path, {}) as w:
        w.write_cdr("/trisect/points", messages[1].msgtype, 1, messages[1].cdr)
        raw: Writer = w._writer
        schema = raw.register_schema("Stat", "jsonschema", b'{"type": "object"}')
        channel = raw.register_channel("/trisect/points_json", "json", schema)
        raw.add_message(channel, 2, b'{"a": 1}', 2)
    assert [m.cdr for m in open_recording(path, topics=None).messages()] == [messages[1].cdr]


def test_truncated_mcap(tmp_path: Path) -> None:
    """Cut a 10 s recording (several 1 MiB chunks) at 60 %: the complete chunks are read."""
    full, cut = tmp_path / "full.mcap", tmp_path / "cut.mcap"
    data = make_recording(full, seconds=4.0, seed=1).read_bytes()
    cut.write_bytes(data[: int(len(data) * 0.6)])
    expected = list(open_recording(full).messages())
    rec = open_recording(cut)
    assert rec.metadata["seed"] == "1" and len(rec.topics) == 3
    got: list[RecordedMessage] = []
    with pytest.raises(RecordingError, match=r"cut\.mcap: truncated after \d+ bytes"):
        got.extend(rec.messages())
    assert 0 < len(got) < len(expected)
    assert got == expected[: len(got)]
    bad = tmp_path / "bad.mcap"  # bytes zeroed inside the first chunk: CRC check fails
    bad.write_bytes(data[: len(data) // 4] + bytes(1000) + data[len(data) // 4 + 1000 :])
    with pytest.raises(RecordingError, match=r"bad\.mcap: corrupt"):
        list(open_recording(bad).messages())
    short = tmp_path / "short.mcap"
    short.write_bytes(data[:4000])
    with pytest.raises(RecordingError, match=r"short\.mcap: contains none .*truncated"):
        open_recording(short)


def test_errors_name_the_file(tmp_path: Path, tank: Path) -> None:
    text, empty = tmp_path / "notes.txt", tmp_path / "empty.mcap"
    text.write_text("hello, not a recording\n")
    empty.write_bytes(b"")
    fake = tmp_path / "fake.mcap"
    fake.write_text("{}")
    badbag = tmp_path / "bad.bag"
    badbag.write_bytes(b"#ROSBAG V2.0\n garbage")
    cases = {
        tmp_path / "missing.mcap": "no such file",
        text: "not a recording: expected an MCAP file, a ROS 1 .bag or a ROS 2 bag folder",
        empty: "empty file",
        fake: "not an MCAP file (bad magic)",
        badbag: "cannot read the ROS 1 bag",
        tmp_path: "folder without metadata.yaml",
    }
    for path, what in cases.items():
        with pytest.raises(RecordingError) as err:
            open_recording(path)
        assert str(path) in str(err.value) and what in str(err.value)
    none = tmp_path / "other_topics.mcap"
    with RecordingWriter(none, {}) as w:
        w.write_groundtruth(1, (0, 0, 0), (0, 0, 0, 1))
    with pytest.raises(RecordingError, match="other_topics.mcap: contains none of the topics"):
        open_recording(none, topics=("/trisect/points", "/tf_static"))
    with RecordingWriter(tmp_path / "bad.mcap", {}) as w, pytest.raises(ValueError, match="shape"):
        w.write_points(1, np.zeros((4, 2)))


@pytest.mark.parametrize("layout", ["xyz float32 packed", "xyz + intensity", "zyx order",
                                    "float64", "big-endian", "x after padding"])
def test_decode_points_reads_every_field_layout(layout: str) -> None:
    """Drivers lay out PointCloud2 fields differently; each gives the same points, and points
    with a NaN or inf coordinate are dropped and counted."""
    from wavegrasp.recording_io.ros_msgs import FLOAT32, FLOAT64, decode_points

    rng = np.random.default_rng(3)
    xyz = rng.normal(size=(50, 3)).astype(np.float32)
    xyz[7, 1], xyz[20, 2] = np.nan, np.inf
    size, kind, order, pad, extra = 4, FLOAT32, "xyz", 0, 0
    big = layout == "big-endian"
    if layout == "xyz + intensity":
        extra = 4
    elif layout == "zyx order":
        order = "zyx"
    elif layout == "float64":
        size, kind = 8, FLOAT64
    elif layout == "x after padding":
        pad = 4
    step = pad + 3 * size + extra
    dtype = np.dtype({"names": list("xyz"), "formats": [f"{'>' if big else '<'}f{size}"] * 3,
                      "offsets": [pad + size * order.index(c) for c in "xyz"], "itemsize": step})
    raw = np.zeros(len(xyz), dtype)
    for i, c in enumerate("xyz"):
        raw[c] = xyz[:, i]
    t = ros2_typestore().types
    fields = [t["sensor_msgs/msg/PointField"](name=c, offset=pad + size * order.index(c),
                                              datatype=kind, count=1) for c in "xyz"]
    header = t["std_msgs/msg/Header"](stamp=t["builtin_interfaces/msg/Time"](sec=5, nanosec=7),
                                      frame_id="cam")
    msg = t["sensor_msgs/msg/PointCloud2"](
        header=header, height=1, width=len(xyz), fields=fields, is_bigendian=big,
        point_step=step, row_step=step * len(xyz), data=raw.view(np.uint8).reshape(-1),
        is_dense=False)
    cloud = decode_points(bytes(ros2_typestore().serialize_cdr(
        msg, "sensor_msgs/msg/PointCloud2")))
    finite = np.isfinite(xyz).all(axis=1)
    assert cloud.points.dtype == np.float32 and cloud.points.shape == (48, 3)
    np.testing.assert_array_equal(cloud.points, xyz[finite])
    assert cloud.dropped_nonfinite == 2 and cloud.frame_id == "cam"
    assert cloud.stamp_ns == 5_000_000_007


def test_a_pose_decodes_to_its_quaternion_as_sent_and_a_bad_one_is_named() -> None:
    from scipy.spatial.transform import Rotation

    from wavegrasp.recording_io.ros_msgs import decode_pose, decode_pose_quaternion

    t = ros2_typestore().types

    def pose(q: list[float], p: list[float]) -> bytes:
        msg = t["geometry_msgs/msg/PoseStamped"](
            header=t["std_msgs/msg/Header"](stamp=t["builtin_interfaces/msg/Time"](
                sec=3, nanosec=5), frame_id="world"),
            pose=t["geometry_msgs/msg/Pose"](
                position=t["geometry_msgs/msg/Point"](x=p[0], y=p[1], z=p[2]),
                orientation=t["geometry_msgs/msg/Quaternion"](x=q[0], y=q[1], z=q[2], w=q[3])))
        return bytes(ros2_typestore().serialize_cdr(msg, "geometry_msgs/msg/PoseStamped"))

    q = Rotation.from_euler("xyz", [0.3, -0.2, 1.1]).as_quat()
    cdr = pose(list(q), [0.1, -0.2, 0.5])
    position, quat, stamp = decode_pose_quaternion(cdr)
    T, _, stamp_m = decode_pose(cdr)
    assert stamp == stamp_m == 3_000_000_005
    np.testing.assert_allclose(quat, q)
    np.testing.assert_allclose(position, T[:3, 3])
    np.testing.assert_allclose(Rotation.from_quat(quat).as_matrix(), T[:3, :3], atol=1e-12)
    with pytest.raises(ValueError, match="not a unit quaternion"):
        decode_pose_quaternion(pose([0.0, 0.0, 0.0, 2.0], [0.0, 0.0, 0.0]))
    with pytest.raises(ValueError, match="transform has NaN or inf"):
        decode_pose_quaternion(pose([0.0, 0.0, 0.0, 1.0], [float("nan"), 0.0, 0.0]))
    with pytest.raises(ValueError, match="not a valid geometry_msgs/msg/PoseStamped"):
        decode_pose_quaternion(b"\x00\x01 not a pose")

"""Write recordings: an MCAP per the recording contract, and ROS 1 / ROS 2 bag copies of one.

See ARCHITECTURE.md, "Recordings (contract)". Every ROS channel is CDR with a ros2msg schema (the
rosbags-generated definition with its dependencies); log time = publish time = the header stamp.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping, Sequence
from pathlib import Path
from types import TracebackType

import numpy as np
from mcap.writer import Writer
from rosbags.rosbag1 import Writer as Ros1Writer
from rosbags.rosbag2 import StoragePlugin
from rosbags.rosbag2 import Writer as Ros2Writer

from .reader import RecordedMessage
from .typestore import check_msgtype, ros1_typestore, ros2_msgdef, ros2_typestore

__all__ = ["METADATA_NAME", "RecordingWriter", "ros2_msgdef", "write_ros1_bag", "write_ros2_bag"]

METADATA_NAME = "wavegrasp.recording"
FLOAT32 = 7  # sensor_msgs/msg/PointField.FLOAT32


def check_stamp(stamp_ns: int) -> int:
    """Return `stamp_ns` (int, nanoseconds since the epoch) or raise ValueError if negative."""
    if int(stamp_ns) != stamp_ns or stamp_ns < 0:
        raise ValueError(f"stamp_ns must be a non-negative integer of nanoseconds, got {stamp_ns}")
    return int(stamp_ns)


def check_vector(values: Sequence[float], n: int, name: str) -> np.ndarray:
    """Return `values` as a finite float64 array of shape (n,) or raise ValueError."""
    arr = np.asarray(values, dtype=np.float64)
    if arr.shape != (n,) or not np.isfinite(arr).all():
        raise ValueError(f"{name} must be {n} finite numbers, got {values!r}")
    return arr


def check_quaternion(xyzw: Sequence[float]) -> np.ndarray:
    """Return a unit quaternion (x, y, z, w) as shape (4,), or raise ValueError if not unit."""
    q = check_vector(xyzw, 4, "quaternion (x, y, z, w)")
    if abs(np.linalg.norm(q) - 1.0) > 1e-3:
        raise ValueError(f"quaternion (x, y, z, w) must have norm 1, got {np.linalg.norm(q):.6f}")
    return q


def check_points(points: np.ndarray) -> np.ndarray:
    """Return `points` as little-endian float32 of shape (n, 3), or raise ValueError."""
    arr = np.asarray(points)
    if arr.ndim != 2 or arr.shape[1] != 3:
        raise ValueError(f"points must have shape (n, 3), got {arr.shape}")
    return np.ascontiguousarray(arr, dtype="<f4")


def check_metadata(metadata: Mapping[str, str]) -> dict[str, str]:
    """Return `metadata` as a dict, or raise ValueError if a key or value is not a str."""
    bad = [k for k, v in metadata.items() if not isinstance(k, str) or not isinstance(v, str)]
    if bad:
        raise ValueError(f"metadata keys and values must be str; not so for {bad!r}")
    return dict(metadata)


def _header(stamp_ns: int, frame_id: str) -> object:
    t = ros2_typestore().types
    sec, nanosec = divmod(stamp_ns, 1_000_000_000)
    return t["std_msgs/msg/Header"](
        stamp=t["builtin_interfaces/msg/Time"](sec=sec, nanosec=nanosec), frame_id=frame_id
    )


class RecordingWriter:
    """Context manager writing an MCAP recording (ROS 2 profile, zstd chunks).

    Parameters
    ----------
    path : str or Path
        The MCAP file to create (overwritten if it exists).
    metadata : dict of str to str
        Written as the metadata record ``wavegrasp.recording`` (wave, object, seed, generator...).
    """

    def __init__(self, path: str | Path, metadata: Mapping[str, str]) -> None:
        self.path = Path(path)
        self._metadata = check_metadata(metadata)
        self._channels: dict[str, tuple[str, int]] = {}  # topic -> (msgtype, channel id)
        self._schemas: dict[str, int] = {}
        self._sequence: dict[str, int] = {}
        self._file = open(self.path, "wb")  # noqa: SIM115 (closed in close())
        self._writer = Writer(self._file)
        self._writer.start(profile="ros2", library="wavegrasp.recording_io")
        self._writer.add_metadata(METADATA_NAME, self._metadata)

    def __enter__(self) -> RecordingWriter:
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType
    ) -> None:
        self.close()

    def close(self) -> None:
        """Write the summary and footer and close the file (idempotent)."""
        if not self._file.closed:
            self._writer.finish()
            self._file.close()

    def add_metadata(self, name: str, metadata: Mapping[str, str]) -> None:
        """Add another metadata record (for facts known only once the data is written)."""
        self._writer.add_metadata(name, check_metadata(metadata))

    def _channel(self, topic: str, msgtype: str) -> int:
        if topic in self._channels:
            known, channel_id = self._channels[topic]
            if known != msgtype:
                raise ValueError(f"topic {topic} already carries {known}, not {msgtype}")
            return channel_id
        if msgtype not in self._schemas:
            data = ros2_msgdef(msgtype).encode()
            self._schemas[msgtype] = self._writer.register_schema(msgtype, "ros2msg", data)
        channel_id = self._writer.register_channel(topic, "cdr", self._schemas[msgtype])
        self._channels[topic] = (msgtype, channel_id)
        return channel_id

    def write_cdr(self, topic: str, msgtype: str, stamp_ns: int, cdr: bytes) -> None:
        """Write one CDR-serialized message of ROS 2 type `msgtype` at log time `stamp_ns` (ns)."""
        stamp_ns = check_stamp(stamp_ns)
        channel_id = self._channel(topic, msgtype)
        seq = self._sequence.get(topic, 0)
        self._sequence[topic] = seq + 1
        self._writer.add_message(channel_id, stamp_ns, bytes(cdr), stamp_ns, seq)

    def _write(self, topic: str, msgtype: str, stamp_ns: int, msg: object) -> None:
        self.write_cdr(topic, msgtype, stamp_ns, ros2_typestore().serialize_cdr(msg, msgtype))

    def write_points(
        self, stamp_ns: int, points: np.ndarray, frame_id: str = "trisect_optical"
    ) -> None:
        """Write `/trisect/points`, a sensor_msgs/msg/PointCloud2 (x, y, z float32, height 1).

        Parameters
        ----------
        stamp_ns : int
            Capture time, nanoseconds since the epoch.
        points : array, shape (n, 3), metres, frame `frame_id` (trisect_optical: z fwd, y down)
        """
        from .ros_msgs import encode_points  # it builds on this module's checks

        self.write_cdr("/trisect/points", "sensor_msgs/msg/PointCloud2", stamp_ns,
                       encode_points(points, stamp_ns, frame_id))

    def write_organized_points(self, stamp_ns: int, image: np.ndarray, height: int, width: int,
                               frame_id: str = "trisect_optical") -> None:
        """Write `/trisect/points` as an organized PointCloud2 (height x width, NaN where
        empty, PCL's XYZRGB layout). image : array, shape (height * width, 3), metres."""
        from .ros_msgs import encode_organized_points

        self.write_cdr("/trisect/points", "sensor_msgs/msg/PointCloud2", stamp_ns,
                       encode_organized_points(image, height, width, stamp_ns, frame_id))

    def write_tf_static(
        self,
        stamp_ns: int,
        transforms: Iterable[tuple[str, str, Sequence[float], Sequence[float]]],
    ) -> None:
        """Write `/tf_static`, a tf2_msgs/msg/TFMessage.

        Parameters
        ----------
        stamp_ns : int
            Nanoseconds since the epoch.
        transforms : iterable of (parent, child, translation, rotation)
            translation : shape (3,), metres, the child's origin in the parent frame;
            rotation : shape (4,), unit quaternion x, y, z, w, the child's axes in the parent.
        """
        t = ros2_typestore().types
        msgs = []
        for parent, child, xyz, xyzw in transforms:
            p, q = check_vector(xyz, 3, "translation"), check_quaternion(xyzw)
            transform = t["geometry_msgs/msg/Transform"](
                translation=t["geometry_msgs/msg/Vector3"](x=p[0], y=p[1], z=p[2]),
                rotation=t["geometry_msgs/msg/Quaternion"](x=q[0], y=q[1], z=q[2], w=q[3]),
            )
            msgs.append(t["geometry_msgs/msg/TransformStamped"](
                header=_header(check_stamp(stamp_ns), parent), child_frame_id=child,
                transform=transform,
            ))
        msg = t["tf2_msgs/msg/TFMessage"](transforms=msgs)
        self._write("/tf_static", "tf2_msgs/msg/TFMessage", stamp_ns, msg)

    def write_groundtruth(
        self,
        stamp_ns: int,
        position: Sequence[float],
        orientation: Sequence[float],
        frame_id: str = "world",
    ) -> None:
        """Write `/groundtruth/object`, a geometry_msgs/msg/PoseStamped.

        Parameters
        ----------
        stamp_ns : int
            Nanoseconds since the epoch.
        position : shape (3,), metres, the object's centroid in `frame_id`
        orientation : shape (4,), unit quaternion x, y, z, w, the object's axes in `frame_id`
        """
        p, q = check_vector(position, 3, "position"), check_quaternion(orientation)
        t = ros2_typestore().types
        pose = t["geometry_msgs/msg/Pose"](
            position=t["geometry_msgs/msg/Point"](x=p[0], y=p[1], z=p[2]),
            orientation=t["geometry_msgs/msg/Quaternion"](x=q[0], y=q[1], z=q[2], w=q[3]),
        )
        msg = t["geometry_msgs/msg/PoseStamped"](
            header=_header(check_stamp(stamp_ns), frame_id), pose=pose
        )
        self._write("/groundtruth/object", "geometry_msgs/msg/PoseStamped", stamp_ns, msg)


def write_ros1_bag(path: str | Path, messages: Iterable[RecordedMessage]) -> Path:
    """Write `messages` to a new ROS 1 bag (CDR converted to ROS 1 with rosbags' type stores).

    Message types must be known to ROS 1 Noetic and ROS 2 Humble (all the contract's are);
    otherwise ValueError. The bag's definitions and md5sums are Noetic's. Returns the bag path.
    """
    ros1, ros2 = ros1_typestore(), ros2_typestore()
    connections = {}
    with Ros1Writer(Path(path)) as bag:
        for m in messages:
            if m.topic not in connections:
                check_msgtype(m.msgtype, ros1)
                check_msgtype(m.msgtype, ros2)
                connections[m.topic] = bag.add_connection(m.topic, m.msgtype, typestore=ros1)
            raw = ros2.cdr_to_ros1(m.cdr, m.msgtype)
            bag.write(connections[m.topic], m.log_time_ns, raw)
    return Path(path)


def write_ros2_bag(path: str | Path, messages: Iterable[RecordedMessage]) -> Path:
    """Write `messages` (CDR, unchanged) to a new ROS 2 bag folder, sqlite3 storage, version 9.

    Message types must be known to ROS 2 Humble; otherwise ValueError. Returns the folder path.
    """
    ros2 = ros2_typestore()
    connections = {}
    with Ros2Writer(Path(path), version=9, storage_plugin=StoragePlugin.SQLITE3) as bag:
        for m in messages:
            if m.topic not in connections:
                check_msgtype(m.msgtype, ros2)
                connections[m.topic] = bag.add_connection(m.topic, m.msgtype, typestore=ros2)
            bag.write(connections[m.topic], m.log_time_ns, m.cdr)
    return Path(path)

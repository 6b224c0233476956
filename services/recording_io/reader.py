"""Open a recording (MCAP, ROS 1 bag or ROS 2 bag folder) and iterate its messages as CDR.

Failures of any kind surface as `RecordingError`, whose message (one line) names the file and the
problem; a truncated MCAP yields its complete messages first, then raises `TruncatedRecording`
(see `mcap_read`, whose `read_mcap` also reads any MCAP's raw messages that way).
"""

from __future__ import annotations

from collections.abc import Iterable
from pathlib import Path

from .bag_source import BagRecording
from .mcap_read import MAGIC, check_mcap, read_mcap
from .mcap_source import McapRecording
from .recording import (
    CONTRACT_TOPICS,
    NOT_A_RECORDING,
    ROS1_MAGIC,
    RecordedMessage,
    Recording,
    RecordingError,
    TruncatedRecording,
    check_path,
)

__all__ = ["CONTRACT_TOPICS", "RecordedMessage", "Recording", "RecordingError",
           "TruncatedRecording", "check_path", "open_for_replay", "open_recording", "read_mcap"]

CAMERA = ("/trisect/points", "sensor_msgs/msg/PointCloud2")  # what the pipeline runs on
#: How long after the first camera frame its static transform may come (a recorder that
#: started the camera's driver first).
TRANSFORM_WAIT_NS = 2_000_000_000


def open_recording(
    path: str | Path, topics: Iterable[str] | None = CONTRACT_TOPICS
) -> Recording:
    """Open a recording and select the ROS 2 (CDR) channels of `topics`.

    Parameters
    ----------
    path : str or Path
        An MCAP file (read with the `mcap` library: JSON or other non-CDR channels are skipped),
        a ROS 1 ``.bag`` file, or a ROS 2 bag folder (with ``metadata.yaml``; sqlite3 or mcap).
    topics : iterable of str, or None
        Topics to read; None reads every CDR topic. Default: the recording contract's.

    Returns
    -------
    Recording
        With `.format`, `.metadata`, `.topics`, `.message_count`, `.start_ns`, `.end_ns`,
        `.msgdef(msgtype)` and `.messages()` (log-time order).

    Raises
    ------
    RecordingError
        If the path is missing, not a recording, unreadable, or has none of `topics`.
    """
    path = Path(path)
    wanted = None if topics is None else tuple(topics)
    head = check_path(path)
    if path.is_dir():
        if not (path / "metadata.yaml").is_file():
            files = sorted(p.name for p in path.iterdir() if p.suffix in (".db3", ".mcap"))
            has = f" (it holds {', '.join(files[:3])})" if files else ""
            raise RecordingError(f"{path}: folder without metadata.yaml, {NOT_A_RECORDING}{has}")
        return BagRecording.open(path, "ros2", wanted)
    if head.startswith(MAGIC):
        return McapRecording.open(path, wanted)
    if len(head) < len(MAGIC) and MAGIC.startswith(head):
        check_mcap(path)  # says where it is cut
    if path.suffix == ".bag" or head == ROS1_MAGIC:
        if path.suffix != ".bag":
            raise RecordingError(f"{path}: a ROS 1 bag must be named *.bag to be read")
        if head != ROS1_MAGIC:
            raise RecordingError(f"{path}: not a ROS 1 bag (bad magic: starts with "
                                 f"{head!r}, not {ROS1_MAGIC!r})")
        return BagRecording.open(path, "ros1", wanted)
    if path.suffix == ".mcap":
        raise RecordingError(f"{path}: not an MCAP file (bad magic)")
    raise RecordingError(f"{path}: {NOT_A_RECORDING}")


def open_for_replay(path: str | Path) -> Recording:
    """`open_recording` with the contract's topics, and require the camera's point clouds (what
    `wavegrasp player` and `wavegrasp up` replay). Raises RecordingError naming the file and what
    is wrong; a recording that can be read only in part opens with `problem` set."""
    recording = open_recording(path)
    recording.require(*CAMERA)
    return recording


def check_camera_transform(recording: Recording) -> None:
    """Raise RecordingError naming the file and the camera's frame unless ``/tf_static``
    places that frame (the first cloud's) in ``world`` by ``TRANSFORM_WAIT_NS`` after the first
    cloud: perception places every point with it. Reads only the recording's start."""
    from .ros_msgs import StaticTransforms, decode_tf, view_points

    tf, frame, first_ns = StaticTransforms(), None, 0
    try:
        for msg in recording.messages():
            if msg.topic == "/tf_static":
                tf.update(decode_tf(msg.cdr))
            elif msg.topic == CAMERA[0] and frame is None:
                frame, first_ns = view_points(msg.cdr).frame_id, msg.log_time_ns
            if frame is not None:
                try:
                    tf.lookup("world", frame)
                    return
                except ValueError:
                    if msg.log_time_ns - first_ns > TRANSFORM_WAIT_NS:
                        break
    except TruncatedRecording:  # cut before it could tell: the replay warns of the cut
        return
    except ValueError as exc:  # a message that does not decode
        raise RecordingError(f"{recording.path}: {exc}") from None
    if frame is not None:
        raise RecordingError(
            f"{recording.path}: no /tf_static transform from the camera's frame {frame!r} to "
            "'world' (perception places every point with it): record the camera's static "
            "transforms too")

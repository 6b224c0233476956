"""Open a recording (MCAP, ROS 1 bag or ROS 2 bag folder) and iterate its messages as CDR.

Failures of any kind surface as `RecordingError`, whose message names the file and the problem;
a truncated MCAP yields its complete messages first (see `mcap_source`).
"""

from __future__ import annotations

from collections.abc import Iterable
from pathlib import Path

from .bag_source import BagRecording
from .mcap_source import MAGIC, McapRecording
from .recording import CONTRACT_TOPICS, RecordedMessage, Recording, RecordingError

__all__ = ["CONTRACT_TOPICS", "RecordedMessage", "Recording", "RecordingError", "open_recording"]

ROS1_MAGIC = b"#ROSBAG V2.0"
NOT_A_RECORDING = "not a recording: expected an MCAP file, a ROS 1 .bag or a ROS 2 bag folder"


def check_path(path: Path) -> bytes:
    """Return the first bytes of file `path` ('' for a folder), or raise RecordingError if it is
    missing, unreadable or empty."""
    if not path.exists():
        raise RecordingError(f"{path}: no such file")
    if path.is_dir():
        return b""
    try:
        with open(path, "rb") as f:
            head = f.read(len(ROS1_MAGIC))
    except OSError as err:
        raise RecordingError(f"{path}: cannot read: {err.strerror}") from None
    if not head:
        raise RecordingError(f"{path}: empty file (0 bytes), {NOT_A_RECORDING}")
    return head


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
            raise RecordingError(f"{path}: folder without metadata.yaml, {NOT_A_RECORDING}")
        return BagRecording.open(path, "ros2", wanted)
    if head.startswith(MAGIC):
        return McapRecording.open(path, wanted)
    if path.suffix == ".bag" or head == ROS1_MAGIC:
        if path.suffix != ".bag":
            raise RecordingError(f"{path}: a ROS 1 bag must be named *.bag to be read")
        return BagRecording.open(path, "ros1", wanted)
    if path.suffix == ".mcap":
        raise RecordingError(f"{path}: not an MCAP file (bad magic)")
    raise RecordingError(f"{path}: {NOT_A_RECORDING}")

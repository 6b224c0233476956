"""What every recording reader returns: `Recording`, `RecordedMessage`, `RecordingError`."""

from __future__ import annotations

import functools
import struct
from collections.abc import Iterator
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Literal

from wavegrasp.recording_io.typestore import ros2_typestore

CONTRACT_TOPICS = ("/trisect/points", "/tf_static", "/groundtruth/object")
Format = Literal["mcap", "ros1", "ros2"]
ROS1_MAGIC = b"#ROSBAG V2.0"
NOT_A_RECORDING = "not a recording: expected an MCAP file, a ROS 1 .bag or a ROS 2 bag folder"
MAX_DETAIL = 300  # characters of a library's error message quoted in ours


class RecordingError(Exception):
    """A recording cannot be read (or not all of it); the message, one line, names the file and
    what is wrong."""


class TruncatedRecording(RecordingError):
    """The recording ends early (its writer was stopped mid-write); raised after every message
    before the cut was read."""


def describe(err: BaseException) -> str:
    """Return 'ExceptionType: message' (or just the type) for a library's exception, on one
    line and at most about MAX_DETAIL characters."""
    text = " ".join(str(err).split())
    if len(text) > MAX_DETAIL:
        text = text[:MAX_DETAIL] + "..."
    return f"{type(err).__name__}: {text}" if text else type(err).__name__


def check_path(path: Path) -> bytes:
    """Return the first bytes of file `path` (b'' for a folder), or raise RecordingError if it is
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


@dataclass(frozen=True)
class RecordedMessage:
    """One ROS message of a recording.

    Attributes
    ----------
    topic : str
        e.g. '/trisect/points'.
    msgtype : str
        ROS 2 type name, e.g. 'sensor_msgs/msg/PointCloud2'.
    log_time_ns : int
        Log time, nanoseconds since the epoch (the header stamp in our recordings).
    cdr : bytes
        The CDR serialization (with its 4-byte encapsulation header), as stored in MCAP and
        ROS 2 bags, or converted from ROS 1 serialization for ROS 1 bags.
    """

    topic: str
    msgtype: str
    log_time_ns: int
    cdr: bytes

    def shifted(self, offset_ns: int) -> RecordedMessage:
        """The message ``offset_ns`` later: its log time, and its header's stamp if it opens
        with a ``std_msgs/Header`` (a cloud, a pose; static transforms keep theirs)."""
        if not offset_ns:
            return self
        cdr = self.cdr
        if has_header(self.msgtype) and len(cdr) >= 12:
            order = "<" if cdr[1] & 1 else ">"  # the encapsulation's byte order
            sec, nanosec = struct.unpack_from(f"{order}iI", cdr, 4)
            stamp = sec * 1_000_000_000 + nanosec + offset_ns
            cdr = cdr[:4] + struct.pack(f"{order}iI", *divmod(stamp, 1_000_000_000)) + cdr[12:]
        return replace(self, log_time_ns=self.log_time_ns + offset_ns, cdr=cdr)


@functools.cache
def has_header(msgtype: str) -> bool:
    """Whether ``msgtype``'s first field is a ``std_msgs/msg/Header``."""
    fields = ros2_typestore().fielddefs.get(msgtype, ((), ()))[1]
    return bool(fields) and fields[0][1][1] == "std_msgs/msg/Header"


@dataclass
class Recording:
    """An opened recording (see `open_recording`); subclasses implement `messages`.

    Attributes
    ----------
    path : Path
    format : 'mcap', 'ros1' or 'ros2'
    metadata : dict of str to str
        The MCAP metadata record ``wavegrasp.recording``; empty if absent (always so for bags).
    topics : dict of str to str
        topic -> ROS 2 message type, for the requested topics present in the file.
    message_count : int or None
        Messages on those topics, when known without reading the whole file.
    start_ns, end_ns : int or None
        First and last log time in the file (all topics), nanoseconds, when known.
    problem : str or None
        What is wrong with a file that can still be read in part (e.g. truncated), found when it
        was opened; `messages` raises RecordingError where it stops if messages were lost.
    """

    path: Path
    format: Format
    metadata: dict[str, str] = field(default_factory=dict)
    topics: dict[str, str] = field(default_factory=dict)
    message_count: int | None = None
    start_ns: int | None = None
    end_ns: int | None = None
    problem: str | None = None
    _msgdefs: dict[str, str] = field(default_factory=dict, repr=False)

    def msgdef(self, msgtype: str) -> str:
        """Return the ros2msg definition text of `msgtype` (with dependencies), or raise
        RecordingError if the recording has no such type on the requested topics."""
        if msgtype not in self._msgdefs:
            raise RecordingError(f"{self.path}: no message definition for {msgtype}")
        return self._msgdefs[msgtype]

    def messages(self) -> Iterator[RecordedMessage]:
        """Yield the requested topics' messages in log-time order."""
        raise NotImplementedError

    def check_topics(self, requested: tuple[str, ...] | None, why: str | None = None,
                     found: str | None = None) -> None:
        """Raise RecordingError if none of the `requested` topics (None: any) is present; `why`
        (e.g. the file's truncation) and `found` (what the file has instead) are added."""
        if not self.topics:
            wanted = ", ".join(requested) if requested else "any ROS 2 (CDR) topic"
            why = f" ({why})" if why else ""
            found = f"; it has {found}" if found else ""
            raise RecordingError(f"{self.path}: contains none of the topics {wanted}{why}{found}")

    def require(self, topic: str, msgtype: str) -> None:
        """Raise RecordingError unless `topic` is present with type `msgtype`."""
        if self.topics.get(topic) == msgtype:
            return
        has = (f"it has {topic} as {self.topics[topic]}" if topic in self.topics else
               f"it has only {', '.join(sorted(self.topics))}")
        raise RecordingError(f"{self.path}: no {topic} ({msgtype}) to replay: {has}")

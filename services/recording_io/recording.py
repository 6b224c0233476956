"""What every recording reader returns: `Recording`, `RecordedMessage`, `RecordingError`."""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

CONTRACT_TOPICS = ("/trisect/points", "/tf_static", "/groundtruth/object")
Format = Literal["mcap", "ros1", "ros2"]


class RecordingError(Exception):
    """A recording cannot be read; the message names the file and what is wrong."""


def describe(err: BaseException) -> str:
    """Return 'ExceptionType: message' (or just the type) for a library's exception."""
    text = str(err)
    return f"{type(err).__name__}: {text}" if text else type(err).__name__


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
    """

    path: Path
    format: Format
    metadata: dict[str, str] = field(default_factory=dict)
    topics: dict[str, str] = field(default_factory=dict)
    message_count: int | None = None
    start_ns: int | None = None
    end_ns: int | None = None
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

    def check_topics(self, requested: tuple[str, ...] | None, why: str | None = None) -> None:
        """Raise RecordingError if none of the `requested` topics (None: any) is present; `why`
        (e.g. the file's truncation) is appended to the message."""
        if not self.topics:
            wanted = ", ".join(requested) if requested else "any ROS 2 (CDR) topic"
            why = f" ({why})" if why else ""
            raise RecordingError(f"{self.path}: contains none of the topics {wanted}{why}")

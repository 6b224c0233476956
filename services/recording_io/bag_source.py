"""Read ROS 1 bags and ROS 2 bag folders with rosbags' AnyReader, yielding CDR.

ROS 1 messages are converted to CDR byte-wise (`Typestore.ros1_to_cdr`) against the bag's own
definitions with ROS 2's `std_msgs/msg/Header` (no `seq`), as `rosbags-convert` does.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

from rosbags.highlevel import AnyReader
from rosbags.rosbag1.reader import Header, RecordType
from rosbags.typesys import Stores, get_typestore
from rosbags.typesys.store import Typestore

from .recording import (
    RecordedMessage,
    Recording,
    RecordingError,
    TruncatedRecording,
    describe,
)
from .typestore import ros1_typestore, ros2_typestore

KIND = {"ros1": "ROS 1 bag", "ros2": "ROS 2 bag"}


def cdr_typestore(reader: AnyReader) -> Typestore:
    """Return the type store that describes `reader`'s messages as ROS 2 (CDR) types."""
    if reader.is2:
        return reader.typestore
    store = get_typestore(Stores.EMPTY)
    header = ros2_typestore().fielddefs["std_msgs/msg/Header"]
    store.register({**reader.typestore.fielddefs, "std_msgs/msg/Header": header})
    return store


def ros1_truncation(path: Path) -> str | None:
    """Say how ROS 1 bag `path` is cut short if its header places the index past its end (the
    index is written last); None if it is not, or the header cannot be read."""
    try:
        with path.open("rb") as f:
            f.readline()
            index_pos = Header.read(f, RecordType.BAGHEADER).get_uint64("index_pos")
    except Exception:
        return None
    size = path.stat().st_size
    if index_pos < size:
        return None
    return (f"truncated ROS 1 bag: it ends at byte {size}, before its index (due at byte "
            f"{index_pos}); `rosbag reindex` can rebuild the index of what is left")


@dataclass
class BagRecording(Recording):
    """A ROS 1 bag (`format` 'ros1') or ROS 2 bag folder ('ros2'); metadata is always empty."""

    def _reader(self) -> AnyReader:
        store = ros2_typestore() if self.format == "ros2" else ros1_typestore()
        return AnyReader([self.path], default_typestore=store)

    def _fail(self, err: Exception) -> RecordingError:
        cut = ros1_truncation(self.path) if self.format == "ros1" else None
        if cut:
            return TruncatedRecording(f"{self.path}: {cut}")
        return RecordingError(f"{self.path}: cannot read the {KIND[self.format]}: {describe(err)}")

    @classmethod
    def open(cls, path: Path, fmt: str, topics: tuple[str, ...] | None) -> BagRecording:
        """Read the bag's index: topics, types, counts, time range and definitions."""
        rec = cls(path=path, format=fmt)  # type: ignore[arg-type]
        try:
            with rec._reader() as reader:
                conns = [c for c in reader.connections if topics is None or c.topic in topics]
                conns = [c for c in conns if fmt == "ros1" or c.ext.serialization_format == "cdr"]
                store = cdr_typestore(reader)
                rec.topics = {c.topic: c.msgtype for c in conns}
                rec._msgdefs = {t: store.generate_msgdef(t, ros_version=2)[0]
                                for t in set(rec.topics.values())}
                rec.message_count = sum(c.msgcount for c in conns)
                if reader.message_count:
                    rec.start_ns, rec.end_ns = reader.start_time, reader.end_time
        except Exception as err:
            raise rec._fail(err) from None
        rec.check_topics(topics)
        return rec

    def messages(self) -> Iterator[RecordedMessage]:
        """Yield the requested topics' messages in log-time order, as CDR."""
        try:
            with self._reader() as reader:
                conns = [c for c in reader.connections if c.topic in self.topics]
                store = cdr_typestore(reader)
                for conn, stamp, raw in reader.messages(connections=conns):
                    cdr = raw if reader.is2 else store.ros1_to_cdr(raw, conn.msgtype)
                    yield RecordedMessage(conn.topic, conn.msgtype, stamp, bytes(cdr))
        except Exception as err:
            raise self._fail(err) from None

"""Read the CDR channels of an MCAP with the `mcap` library (also files that mix in JSON ones).

Reading goes through `mcap_read.read_mcap`: a complete file (footer and summary) is read through
its index, in log-time order; a file without a summary, or cut short (a recorder killed
mid-write: no footer), is read linearly in file order, which is log-time order for files written
in time order (ours). Opening such a file scans it once (for its channels, metadata and message
counts) and notes in `problem` why it is incomplete. A cut file yields every message of its
complete chunks and then raises TruncatedRecording (a RecordingError) naming the file and the
truncation; the messages of a partly written chunk are lost (chunks are MCAP's unit of
compression).
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

from mcap.records import Channel, Metadata, Schema

from .mcap_read import MAGIC, open_index, read_mcap, scan_mcap
from .recording import RecordedMessage, Recording

__all__ = ["MAGIC", "McapRecording", "is_ros_channel"]

METADATA_NAME = "wavegrasp.recording"
ROS2_SCHEMAS = ("ros2msg", "ros2idl")
FOUND_LIMIT = 6  # channels listed when none is wanted


def is_ros_channel(channel: Channel, schemas: dict[int, Schema]) -> bool:
    """True if `channel` carries CDR messages with a ROS 2 schema."""
    schema = schemas.get(channel.schema_id)
    return channel.message_encoding == "cdr" and schema is not None and (
        schema.encoding in ROS2_SCHEMAS
    )


def describe_channels(channels: list[Channel], schemas: dict[int, Schema]) -> str:
    """'/a (json, jsonschema), /b (protobuf, protobuf)' for the first few `channels`."""
    def one(c: Channel) -> str:
        schema = schemas.get(c.schema_id)
        return f"{c.topic} ({c.message_encoding or 'no encoding'}, " \
               f"{schema.encoding if schema else 'no schema'})"
    text = ", ".join(one(c) for c in channels[:FOUND_LIMIT])
    more = len(channels) - FOUND_LIMIT
    return text + (f" and {more} more" if more > 0 else "")


@dataclass
class McapRecording(Recording):
    """An MCAP recording; see the module docstring for ordering and truncation."""

    _channel_ids: frozenset[int] = field(default=frozenset(), repr=False)

    @classmethod
    def open(cls, path: Path, topics: tuple[str, ...] | None) -> McapRecording:
        """Read the summary (or scan the file) and select the CDR channels of `topics`."""
        rec = cls(path=path, format="mcap")
        indexed = rec._open_indexed()
        if indexed is None:
            schemas, channels, counts = rec._open_scanned()
        else:
            schemas, channels, counts = indexed
        chosen = {i: c for i, c in channels.items() if is_ros_channel(c, schemas) and (
            topics is None or c.topic in topics)}
        rec._channel_ids = frozenset(chosen)
        rec.topics = {c.topic: schemas[c.schema_id].name for c in chosen.values()}
        rec._msgdefs = {s.name: s.data.decode(errors="replace") for s in schemas.values()
                        if s.encoding in ROS2_SCHEMAS and s.name in rec.topics.values()}
        if counts is not None:
            rec.message_count = sum(counts.get(i, 0) for i in chosen)
        others = [c for i, c in sorted(channels.items()) if i not in chosen]
        rec.check_topics(topics, rec.problem,
                         describe_channels(others, schemas) if others else None)
        return rec

    def _open_indexed(
        self,
    ) -> tuple[dict[int, Schema], dict[int, Channel], dict[int, int] | None] | None:
        """Read a complete file's summary and metadata; None if it must be scanned."""
        with open(self.path, "rb") as f:
            index = open_index(f)
            if index is None:
                return None
            reader, summary = index
            try:
                self._set_metadata(list(reader.iter_metadata()))
            except Exception:  # a damaged metadata index: scan the file instead
                return None
        stats = summary.statistics
        if stats is None:
            return summary.schemas, summary.channels, None
        self.start_ns, self.end_ns = stats.message_start_time, stats.message_end_time
        return summary.schemas, summary.channels, stats.channel_message_counts

    def _open_scanned(self) -> tuple[dict[int, Schema], dict[int, Channel], dict[int, int]]:
        """Scan a file without a usable summary; note in `problem` why it stopped early."""
        scan = scan_mcap(self.path)
        self.problem = scan.problem
        self._set_metadata(scan.metadata)
        self.start_ns, self.end_ns = scan.start_ns, scan.end_ns
        return scan.schemas, scan.channels, scan.counts

    def _set_metadata(self, records: list[Metadata]) -> None:
        self.metadata = next((dict(m.metadata) for m in records if m.name == METADATA_NAME), {})

    def messages(self) -> Iterator[RecordedMessage]:
        """Yield the selected CDR messages; raise RecordingError (TruncatedRecording if the file
        is cut short) after the last good one if the file is truncated or corrupt."""
        for _schema, channel, msg in read_mcap(self.path, list(self.topics)):
            if channel.id in self._channel_ids:
                yield RecordedMessage(channel.topic, self.topics[channel.topic], msg.log_time,
                                      bytes(msg.data))

"""Read the CDR channels of an MCAP with the `mcap` library (also files that mix in JSON ones).

A complete file (footer and summary) is read through its index, in log-time order. A file without
a summary, or cut short (a recorder killed mid-write: no footer), is read linearly in file order,
which is log-time order for files written in time order (ours). A cut file yields every message
of its complete chunks and then raises RecordingError naming the file and the truncation; the
messages of a partly written chunk are lost (chunks are MCAP's unit of compression).
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import BinaryIO

from mcap.reader import SeekingReader
from mcap.records import Channel, Message, Metadata, Schema
from mcap.stream_reader import StreamReader

from .recording import RecordedMessage, Recording, RecordingError, describe

MAGIC = b"\x89MCAP0\r\n"
METADATA_NAME = "wavegrasp.recording"
ROS2_SCHEMAS = ("ros2msg", "ros2idl")


def is_ros_channel(channel: Channel, schemas: dict[int, Schema]) -> bool:
    """True if `channel` carries CDR messages with a ROS 2 schema."""
    schema = schemas.get(channel.schema_id)
    return channel.message_encoding == "cdr" and schema is not None and (
        schema.encoding in ROS2_SCHEMAS
    )


@dataclass
class McapRecording(Recording):
    """An MCAP recording; see the module docstring for ordering and truncation."""

    problem: str | None = None  # why the linear scan stopped early (truncated or corrupt)
    _channel_ids: frozenset[int] = field(default=frozenset(), repr=False)
    _indexed: bool = field(default=False, repr=False)  # read by the summary's chunk index

    @classmethod
    def open(cls, path: Path, topics: tuple[str, ...] | None) -> McapRecording:
        """Read the summary (or scan the file) and select the CDR channels of `topics`."""
        with open(path, "rb") as f:
            size = f.seek(0, 2)
            f.seek(max(0, size - len(MAGIC)))
            complete = size > 2 * len(MAGIC) and f.read() == MAGIC
            f.seek(0)
            try:
                reader = SeekingReader(f, validate_crcs=True)
                summary = reader.get_summary() if complete else None
                meta = list(reader.iter_metadata()) if summary else []
            except Exception as err:
                raise RecordingError(f"{path}: corrupt MCAP summary: {describe(err)}") from None
        rec = cls(path=path, format="mcap", _indexed=summary is not None)
        if summary is None:
            schemas, channels, meta = rec._scan(size, complete)
        else:
            schemas, channels = summary.schemas, summary.channels
        rec.metadata = next((dict(m.metadata) for m in meta if m.name == METADATA_NAME), {})
        chosen = {i: c for i, c in channels.items() if is_ros_channel(c, schemas) and (
            topics is None or c.topic in topics)}
        rec._channel_ids = frozenset(chosen)
        rec.topics = {c.topic: schemas[c.schema_id].name for c in chosen.values()}
        rec._msgdefs = {s.name: s.data.decode(errors="replace") for s in schemas.values()
                        if s.encoding in ROS2_SCHEMAS and s.name in rec.topics.values()}
        stats = summary.statistics if summary else None
        if stats is not None:
            rec.message_count = sum(stats.channel_message_counts.get(i, 0) for i in chosen)
            rec.start_ns, rec.end_ns = stats.message_start_time, stats.message_end_time
        rec.check_topics(topics, rec.problem)
        return rec

    def _scan(
        self, size: int, complete: bool
    ) -> tuple[dict[int, Schema], dict[int, Channel], list[Metadata]]:
        """Read the file linearly for its schemas, channels and metadata; note where it ends."""
        schemas: dict[int, Schema] = {}
        channels: dict[int, Channel] = {}
        meta: list[Metadata] = []
        with open(self.path, "rb") as f:
            try:
                for record in StreamReader(f, validate_crcs=True).records:
                    if isinstance(record, Schema):
                        schemas[record.id] = record
                    elif isinstance(record, Channel):
                        channels[record.id] = record
                    elif isinstance(record, Metadata):
                        meta.append(record)
            except Exception as err:
                what = f"truncated after {size} bytes (no footer)" if not complete else "corrupt"
                self.problem = f"{what}: {describe(err)}"
        return schemas, channels, meta

    def messages(self) -> Iterator[RecordedMessage]:
        """Yield the selected CDR messages; raise RecordingError after the last good one if the
        file is truncated or corrupt."""
        count = 0
        with open(self.path, "rb") as f:
            try:
                for channel, msg in self._iter(f):
                    count += 1
                    yield RecordedMessage(channel.topic, self.topics[channel.topic],
                                          msg.log_time, bytes(msg.data))
            except RecordingError:
                raise
            except Exception as err:
                self.problem = self.problem or f"corrupt: {describe(err)}"
        if self.problem:
            raise RecordingError(f"{self.path}: {self.problem}; read {count} messages before it")

    def _iter(self, f: BinaryIO) -> Iterator[tuple[Channel, Message]]:
        if self._indexed:
            reader = SeekingReader(f, validate_crcs=True)
            for _, channel, msg in reader.iter_messages(topics=list(self.topics)):
                if channel.id in self._channel_ids:
                    yield channel, msg
            return
        channels: dict[int, Channel] = {}
        for record in StreamReader(f, validate_crcs=True).records:
            if isinstance(record, Channel):
                channels[record.id] = record
            elif isinstance(record, Message) and record.channel_id in self._channel_ids:
                yield channels[record.channel_id], record

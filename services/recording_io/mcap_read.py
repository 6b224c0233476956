"""Read an MCAP file's messages, also from a file cut short or damaged: what is readable, then why
the rest is not.

A complete file (footer, and a summary with a chunk index that fits the file) is read through its
index in log-time order with mcap's `SeekingReader`. Any other file (a recorder killed mid-write
leaves no summary or footer) is read linearly in file order with mcap's `StreamReader`, chunk by
chunk with CRCs checked, up to the first record that cannot be read; a partly written chunk is
lost (chunks are MCAP's unit of compression and checksum). Then `TruncatedRecording` (the file
ends early) or `RecordingError` (it is corrupt) is raised, naming the file, the byte where it
breaks and how many messages were read before. A file whose data section is whole but whose
summary or footer is cut or damaged reads without error: no message is lost.
"""

from __future__ import annotations

import os
import re
from collections import Counter
from collections.abc import Collection, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import BinaryIO

from mcap.data_stream import ReadDataStream
from mcap.exceptions import EndOfFile, RecordLengthLimitExceeded
from mcap.opcode import Opcode
from mcap.reader import SeekingReader
from mcap.records import Channel, Chunk, DataEnd, McapRecord, Message, Metadata, Schema
from mcap.stream_reader import CRCValidationError, StreamReader, breakup_chunk
from mcap.summary import Summary

from .recording import RecordingError, TruncatedRecording, check_path, describe

MAGIC = b"\x89MCAP0\r\n"
ROS1_MAGIC = b"#ROSBAG V2.0"
RECORD_HEAD = 9  # opcode (1 byte) and length (8)

MessageTuple = tuple[Schema | None, Channel, Message]


@dataclass
class Progress:
    """How far a read got: messages read and the log-time span they cover."""

    count: int = 0
    first_ns: int | None = None
    last_ns: int | None = None

    def add(self, log_time_ns: int) -> None:
        self.count += 1
        self.first_ns = log_time_ns if self.first_ns is None else min(self.first_ns, log_time_ns)
        self.last_ns = log_time_ns if self.last_ns is None else max(self.last_ns, log_time_ns)

    def __str__(self) -> str:
        if not self.count or self.first_ns is None or self.last_ns is None:
            return "no message could be read before it"
        span = (self.last_ns - self.first_ns) / 1e9
        return f"read the {self.count} messages before it (0.0 s to {span:.1f} s)"


@dataclass
class McapScan:
    """What a linear pass over an MCAP found (see `scan_mcap`)."""

    schemas: dict[int, Schema] = field(default_factory=dict)
    channels: dict[int, Channel] = field(default_factory=dict)
    metadata: list[Metadata] = field(default_factory=list)
    counts: Counter[int] = field(default_factory=Counter)  # messages per channel id
    start_ns: int | None = None
    end_ns: int | None = None
    problem: str | None = None  # why the pass stopped early, without the path
    lost: bool = False  # whether messages were lost to it (not just the summary)


def check_mcap(path: Path) -> None:
    """Raise RecordingError unless `path` is a readable file that starts with MCAP's magic."""
    if path.is_dir():
        raise RecordingError(f"{path}: a folder, not an MCAP file")
    head = check_path(path)
    if head.startswith(MAGIC):
        return
    if len(head) < len(MAGIC) and MAGIC.startswith(head):
        raise TruncatedRecording(f"{path}: truncated after {len(head)} bytes, inside the MCAP "
                                 "magic")
    what = ("it is a ROS 1 bag" if head.startswith(ROS1_MAGIC)
            else f"bad magic, it starts with {head[:len(MAGIC)]!r}")
    raise RecordingError(f"{path}: not a readable MCAP file: {what}")


def read_mcap(path: str | Path, topics: Collection[str] | None = None) -> Iterator[MessageTuple]:
    """Yield (schema, channel, message) for the messages of MCAP file `path` on `topics` (None:
    all), through the index when the file is complete, else linearly (module docstring).

    Raises
    ------
    TruncatedRecording
        After the last message before the cut, if the file ends early.
    RecordingError
        If `path` is no MCAP file, or at the first corrupt part of it.
    """
    path = Path(path)
    check_mcap(path)
    progress = Progress()
    with open(path, "rb") as f:
        index = open_index(f)
        source = _indexed(path, f, *index, topics) if index else _linear(path, f, topics)
        try:
            for item in source:
                progress.add(item[2].log_time)
                yield item
        except RecordingError as err:
            raise type(err)(f"{err}; {progress}") from None


def open_index(f: BinaryIO) -> tuple[SeekingReader, Summary] | None:
    """mcap's reader and the summary of open MCAP `f` if it is complete and its chunk index fits
    the file; None if the file must be read linearly."""
    size = os.fstat(f.fileno()).st_size
    f.seek(max(0, size - len(MAGIC)))
    if size < 2 * len(MAGIC) or f.read() != MAGIC:
        return None
    try:
        f.seek(0)
        reader = SeekingReader(f, validate_crcs=True)
        summary = reader.get_summary()
    except Exception:  # a damaged footer or summary: the data section may be whole
        return None
    if summary is None or not summary.chunk_indexes or any(
            c.chunk_start_offset + c.chunk_length > size for c in summary.chunk_indexes):
        return None
    return reader, summary


def _indexed(path: Path, f: BinaryIO, reader: SeekingReader, summary: Summary,
             topics: Collection[str] | None) -> Iterator[MessageTuple]:
    try:
        yield from reader.iter_messages(topics=None if topics is None else list(topics))
    except Exception as err:
        raise RecordingError(f"{path}: corrupt MCAP: {_bad_chunk(f, summary, err)}") from None


def _bad_chunk(f: BinaryIO, summary: Summary, err: Exception) -> str:
    """Find which indexed chunk of `f` fails (after `err` while reading through the index)."""
    chunks = sorted(summary.chunk_indexes, key=lambda c: c.chunk_start_offset)
    t0 = min(c.message_start_time for c in chunks)
    for index in chunks:
        try:
            f.seek(index.chunk_start_offset + RECORD_HEAD)
            breakup_chunk(Chunk.read(ReadDataStream(f)), validate_crc=True)
        except Exception as chunk_err:
            when = (f"its messages from {(index.message_start_time - t0) / 1e9:.1f} s to "
                    f"{(index.message_end_time - t0) / 1e9:.1f} s")
            return (f"the chunk at byte {index.chunk_start_offset} ({when}) "
                    f"{_failure(chunk_err)}")
    return describe(err)


def _linear(path: Path, f: BinaryIO, topics: Collection[str] | None) -> Iterator[MessageTuple]:
    schemas: dict[int, Schema] = {}
    channels: dict[int, Channel] = {}
    for record in walk_records(path, f, []):
        if isinstance(record, Schema):
            schemas[record.id] = record
        elif isinstance(record, Channel):
            channels[record.id] = record
        elif isinstance(record, Message):
            channel = channels.get(record.channel_id)
            if channel is None:
                raise RecordingError(f"{path}: corrupt MCAP: a message on channel "
                                     f"{record.channel_id}, which was never defined")
            if topics is None or channel.topic in topics:
                yield schemas.get(channel.schema_id), channel, record


def scan_mcap(path: Path) -> McapScan:
    """Read MCAP `path` linearly for its schemas, channels, metadata and message counts, noting
    (not raising) why the pass stopped early, if it did."""
    scan = McapScan()
    notes: list[str] = []
    with open(path, "rb") as f:
        try:
            for record in walk_records(path, f, notes):
                _note(scan, record)
        except RecordingError as err:
            scan.problem, scan.lost = str(err).removeprefix(f"{path}: "), True
    if notes:
        scan.problem = notes[0]
    return scan


def _note(scan: McapScan, record: McapRecord) -> None:
    if isinstance(record, Message):
        scan.counts[record.channel_id] += 1
        t = record.log_time
        scan.start_ns = t if scan.start_ns is None else min(scan.start_ns, t)
        scan.end_ns = t if scan.end_ns is None else max(scan.end_ns, t)
    elif isinstance(record, Schema):
        scan.schemas[record.id] = record
    elif isinstance(record, Channel):
        scan.channels[record.id] = record
    elif isinstance(record, Metadata):
        scan.metadata.append(record)


def walk_records(path: Path, f: BinaryIO, after_data: list[str]) -> Iterator[McapRecord]:
    """Yield the records of open MCAP `f` in file order, each chunk broken up into its records.

    At the first record that cannot be read, raise TruncatedRecording (the file ends inside it or
    before it) or RecordingError (corrupt), both naming the file and the byte; if the data section
    was already whole, append the problem to `after_data` and return instead.
    """
    size = os.fstat(f.fileno()).st_size
    at, last = len(MAGIC), "header"  # where the record being read starts; the last one read
    data_end = False
    f.seek(0)
    try:
        for record in StreamReader(f, emit_chunks=True, validate_crcs=True).records:
            if isinstance(record, Chunk):
                yield from breakup_chunk(record, validate_crc=True)
            else:
                yield record
            data_end = data_end or isinstance(record, DataEnd)
            at, last = f.tell(), _words(type(record).__name__)
    except Exception as err:
        truncated = not isinstance(err, RecordLengthLimitExceeded) and not _ends_with_magic(
            f, size) and (isinstance(err, EndOfFile) or _runs_past_end(f, at, size))
        problem = _problem(f, size, at, last, err, truncated)
        if data_end:
            after_data.append(f"{problem} (after the data section: no message is lost)")
            return
        raise (TruncatedRecording if truncated else RecordingError)(f"{path}: {problem}") from None


def _problem(f: BinaryIO, size: int, at: int, last: str, err: Exception,
             truncated: bool) -> str:
    """Say what is wrong with the record of `f` at byte `at` (`err` came from reading it)."""
    if isinstance(err, CRCValidationError) and isinstance(err.record, DataEnd):
        return "corrupt MCAP: its data section fails its CRC check"
    if truncated:
        cut = f"truncated after {size} bytes (no summary or footer)"
        if at >= size:
            return f"{cut}: it ends after a complete {last} record"
        return f"{cut}: it ends inside a {_kind_at(f, at)} that starts at byte {at}"
    return f"corrupt MCAP: the {_kind_at(f, at)} at byte {at} {_failure(err)}"


def _failure(err: Exception) -> str:
    if isinstance(err, CRCValidationError):
        return "fails its CRC check"
    if isinstance(err, EndOfFile):
        return "runs past the end of the file"
    return f"cannot be read ({describe(err)})"


def _kind_at(f: BinaryIO, at: int) -> str:
    """Name the record that starts at byte `at` of `f` by its opcode, e.g. 'chunk'."""
    f.seek(at)
    head = f.read(1)
    if not head:
        return "record"
    try:
        return _words(Opcode(head[0]).name.title().replace("_", ""))
    except ValueError:
        return f"record of unknown type (opcode {head[0]:#04x})"


def _words(camel: str) -> str:
    """'MessageIndex' -> 'message index'."""
    return re.sub(r"(?<!^)(?=[A-Z])", " ", camel).lower()


def _runs_past_end(f: BinaryIO, at: int, size: int) -> bool:
    """Whether the record at byte `at` of `f` ends (by its length field) past `size`."""
    f.seek(at)
    stream = ReadDataStream(f)
    try:
        stream.read1()
        return at + RECORD_HEAD + stream.read8() > size
    except EndOfFile:
        return True


def _ends_with_magic(f: BinaryIO, size: int) -> bool:
    if size < 2 * len(MAGIC):
        return False
    f.seek(size - len(MAGIC))
    return f.read() == MAGIC

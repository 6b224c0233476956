"""Trace headers and the CDR attachment: how every message says where it has been.

Own messages carry ``header.trace``; each service appends its hop (receive time, send time).
CDR messages carry a zenoh attachment laid out like rmw_zenoh's (sequence number, source
timestamp, 16-byte publisher id, little-endian), extended with the recording's log time.
"""

from __future__ import annotations

import hashlib
import struct
import time
from dataclasses import dataclass

from wavegrasp.schemas import Header, Hop

_ATTACHMENT = struct.Struct("<qq16sq")


@dataclass(frozen=True)
class CdrAttachment:
    """Metadata sent with a CDR payload.

    seq : per-key sequence number; source_ns : wall clock, ns, at publish;
    gid : 16-byte publisher id; log_time_ns : recording clock, ns (0 if unknown).
    """

    seq: int
    source_ns: int
    gid: bytes
    log_time_ns: int = 0

    def encode(self) -> bytes:
        return _ATTACHMENT.pack(self.seq, self.source_ns, self.gid, self.log_time_ns)

    @classmethod
    def decode(cls, data: bytes | None) -> CdrAttachment | None:
        """Parse an attachment; None when absent. Raises ValueError when malformed."""
        if data is None:
            return None
        if len(data) < _ATTACHMENT.size - 8:
            raise ValueError(f"attachment of {len(data)} bytes, expected {_ATTACHMENT.size}")
        if len(data) < _ATTACHMENT.size:  # plain rmw_zenoh attachment: no log time
            data = bytes(data) + b"\0" * 8
        att = cls(*_ATTACHMENT.unpack_from(data))
        for name in ("seq", "source_ns", "log_time_ns"):
            if getattr(att, name) < 0:
                raise ValueError(f"attachment {name} is negative: {getattr(att, name)}")
        return att


def publisher_gid(service: str, key: str) -> bytes:
    """A stable 16-byte id for ``service`` publishing on ``key``."""
    return hashlib.blake2b(f"{service}:{key}".encode(), digest_size=16).digest()


def derived_header(source: Header, service: str, recv_ns: int, frame_id: str | None = None,
                   seq: int | None = None) -> Header:
    """A header for a message derived from ``source``: same stamp, trace plus this hop.

    The hop's ``sent_ns`` is filled in by the bus when the message is published.
    """
    return Header(
        seq=source.seq if seq is None else seq,
        stamp_ns=source.stamp_ns,
        frame_id=source.frame_id if frame_id is None else frame_id,
        trace=[*source.trace, Hop(service=service, recv_ns=recv_ns)],
    )


def new_header(service: str, seq: int, stamp_ns: int, frame_id: str = "world") -> Header:
    """A header for a message that starts a chain here (no input it derives from)."""
    return Header(seq=seq, stamp_ns=stamp_ns, frame_id=frame_id,
                  trace=[Hop(service=service, recv_ns=time.time_ns())])


def stamp_sent(header: Header, service: str) -> None:
    """Set this service's hop ``sent_ns`` to now, if the last hop is ours and unsent."""
    if header.trace and header.trace[-1].service == service and header.trace[-1].sent_ns == 0:
        header.trace[-1].sent_ns = time.time_ns()


def check_trace(trace: list[Hop]) -> None:
    """Raise ValueError naming the first hop whose times are missing or run backwards: each
    hop is received, then sent, and not received before the hop ahead of it was sent."""
    for k, hop in enumerate(trace):
        if hop.recv_ns <= 0 or hop.sent_ns < hop.recv_ns:
            raise ValueError(f"hop {k} ({hop.service}): recv_ns {hop.recv_ns}, "
                             f"sent_ns {hop.sent_ns}")
        if k and hop.recv_ns < trace[k - 1].sent_ns:
            raise ValueError(f"hop {k} ({hop.service}) received before hop {k - 1} "
                             f"({trace[k - 1].service}) was sent")


def hop_times_ms(trace: list[Hop]) -> list[tuple[str, float]]:
    """A trace as (hop name, ms): each transfer between two services (``"a -> b"``: a's send
    to b's receipt) and each service's time in hand (``"b"``). Raises ValueError as
    :func:`check_trace` does."""
    check_trace(trace)
    out: list[tuple[str, float]] = []
    for before, hop in zip(trace[:-1], trace[1:], strict=True):
        out.append((f"{before.service} -> {hop.service}", (hop.recv_ns - before.sent_ns) / 1e6))
        out.append((hop.service, (hop.sent_ns - hop.recv_ns) / 1e6))
    return out

"""Our messages to and from CDR bytes directly, byte for byte what rosbags writes.

rosbags' way (:mod:`wavegrasp.schemas.ros` builds its message objects from the model, then
serialises them) cost 20-80 us a small message against 2-15 us for pydantic's JSON, and a
lockstep frame carries dozens (the clock to every service, each one's acknowledgement...):
3.4 s more CPU on a 1042-frame run, every service 0.3-0.7 s (``wavegrasp eval``'s summaries).
Here each model's fields are compiled once into writers and readers of the same layout
(little-endian CDR, XCDR1: primitives aligned to their size from the end of the 4-byte
encapsulation header, counts and string lengths as uint32, an array's values aligned only when
there are any), following :mod:`wavegrasp.schemas.ros`'s mapping field for field. A test
compares the bytes with rosbags' for every message type.
"""

from __future__ import annotations

import struct
import typing
from collections.abc import Callable
from functools import cache
from typing import Any, Literal

import numpy as np
from pydantic import BaseModel

from wavegrasp.schemas import MESSAGE_TYPES, Header
from wavegrasp.schemas.ros import DTYPES, FLAG, NUMBER, TEXT, _entry, _item, _optional, _plain

ENCAPSULATION = b"\x00\x01\x00\x00"
NS = 1_000_000_000
_PRIM = {int: struct.Struct("<q"), float: struct.Struct("<d"), bool: struct.Struct("<?")}
_U32, _TIME, _U8 = struct.Struct("<I"), struct.Struct("<iI"), struct.Struct("<B")


_ZEROS = [bytes(k) for k in range(8)]


class Writer:
    def __init__(self) -> None:
        self.buf = bytearray(ENCAPSULATION)

    def pad(self, n: int) -> None:
        """Zeros up to a multiple of ``n`` (a power of two) from the end of the header."""
        k = (4 - len(self.buf)) & (n - 1)
        if k:
            self.buf += _ZEROS[k]

    def u32(self, value: int) -> None:
        self.pad(4)
        self.buf += _U32.pack(value)

    def string(self, text: str) -> None:
        data = text.encode()
        self.pad(4)
        self.buf += _U32.pack(len(data) + 1)
        self.buf += data
        self.buf.append(0)

    def time(self, ns: int) -> None:
        """A ``builtin_interfaces`` Time or Duration: int32 seconds, uint32 nanoseconds."""
        self.pad(4)
        self.buf += _TIME.pack(*divmod(ns, NS))

    def doubles(self, values: np.ndarray) -> None:
        """A ``float64[]``."""
        self.u32(len(values))
        if len(values):
            self.pad(8)
            self.buf += np.ascontiguousarray(values, dtype="<f8").tobytes()


class Reader:
    def __init__(self, data: bytes | memoryview) -> None:
        self.data = data if isinstance(data, bytes) else bytes(data)
        self.pos, self.end = 4, len(self.data)
        if self.data[:4] != ENCAPSULATION:
            raise ValueError(f"not little-endian CDR (encapsulation header {self.data[:4].hex()})")

    def take(self, n: int, align: int = 1) -> int:
        """Skip the padding to ``align`` (a power of two), then ``n`` bytes; returns where
        they start."""
        start = self.pos + ((4 - self.pos) & (align - 1))
        if start + n > self.end:
            raise ValueError(f"ends at byte {self.end}, {n} more needed at {start}")
        self.pos = start + n
        return start

    def need(self, n: int) -> None:
        if self.pos + n > self.end:
            raise ValueError(f"ends at byte {self.end}, {n} more needed at {self.pos}")

    def u32(self) -> int:
        return _U32.unpack_from(self.data, self.take(4, 4))[0]

    def time(self) -> tuple[int, int]:
        """A Time or Duration: (seconds, nanoseconds)."""
        return _TIME.unpack_from(self.data, self.take(8, 4))

    def doubles(self) -> np.ndarray:
        """A ``float64[]`` (read-only, on the message's bytes)."""
        n = self.u32()
        if not n:
            return np.zeros(0)
        return np.frombuffer(self.data, "<f8", n, self.take(8 * n, 8))

    def string(self) -> str:
        at = self.pos + ((4 - self.pos) & 3)
        if at + 4 > self.end:
            raise ValueError(f"ends at byte {self.end}, a string's length needed at {at}")
        n = _U32.unpack_from(self.data, at)[0]
        at += 4
        if n < 1 or at + n > self.end or self.data[at + n - 1] != 0:
            raise ValueError(f"string of {n} bytes at byte {at} past the end or unterminated")
        self.pos = at + n
        return self.data[at:at + n - 1].decode()

    def count(self, least_bytes: int) -> int:
        """A sequence's length, refused when the rest cannot hold that many elements."""
        n = self.u32()
        if n * least_bytes > self.end - self.pos:
            raise ValueError(f"sequence of {n} at byte {self.pos} longer than the message")
        return n


Encode = Callable[[Writer, Any], None]
Decode = Callable[[Reader], Any]


def _scalar(kind: Any) -> tuple[Encode, Decode]:
    if kind is str or typing.get_origin(kind) is Literal:
        return (lambda w, v: w.string(v)), (lambda r: r.string())
    s = _PRIM[kind]

    size, pack, unpack = s.size, s.pack, s.unpack_from

    def enc(w: Writer, v: Any) -> None:
        w.pad(size)
        w.buf += pack(v)
    return enc, (lambda r: unpack(r.data, r.take(size, size))[0])


def _array(kind: Any) -> tuple[Encode, Decode]:
    """``kind[]`` of a number or a flag: count, then the values aligned (if any)."""
    dtype = np.dtype(DTYPES[kind]).newbyteorder("<")
    size = dtype.itemsize

    def enc(w: Writer, v: Any) -> None:
        w.u32(len(v))
        if len(v):
            w.pad(size)
            w.buf.extend(np.asarray(v, dtype=dtype).tobytes())

    def dec(r: Reader) -> list:
        n = r.count(size)
        if not n:
            return []
        return np.frombuffer(r.data, dtype, n, r.take(n * size, size)).tolist()
    return enc, dec


def _sequence(one: tuple[Encode, Decode], least_bytes: int) -> tuple[Encode, Decode]:
    enc_one, dec_one = one

    def enc(w: Writer, v: Any) -> None:
        w.u32(len(v))
        for x in v:
            enc_one(w, x)
    return enc, (lambda r: [dec_one(r) for _ in range(r.count(least_bytes))])


def _dict(value: Any) -> tuple[Encode, Decode]:
    entry = _entry(value)
    if entry == "ValueEntry":
        num, flag = _PRIM[float], _PRIM[bool]

        def enc_one(w: Writer, kv: tuple[str, Any]) -> None:
            k, v = kv
            w.string(k)
            kind = FLAG if isinstance(v, bool) else TEXT if isinstance(v, str) else NUMBER
            w.buf.extend(_U8.pack(kind))
            w.pad(8)
            w.buf.extend(num.pack(float(v) if kind == NUMBER else 0.0))
            w.string(v if kind == TEXT else "")
            w.buf.extend(flag.pack(v if kind == FLAG else False))

        def dec_one(r: Reader) -> tuple[str, Any]:
            k = r.string()
            kind = r.data[r.take(1)]
            number = num.unpack_from(r.data, r.take(8, 8))[0]
            text = r.string()
            is_set = bool(r.data[r.take(1)])
            if kind > FLAG:
                raise ValueError(f"ValueEntry {k!r}: kind {kind} is none of 0, 1, 2")
            return k, (number, text, is_set)[kind]
    else:
        enc_value, dec_value = _scalar({"FloatEntry": float, "CountEntry": int}.get(entry, str))

        def enc_one(w: Writer, kv: tuple[str, Any]) -> None:
            w.string(kv[0])
            enc_value(w, kv[1])

        def dec_one(r: Reader) -> tuple[str, Any]:
            return r.string(), dec_value(r)
    enc, dec = _sequence((enc_one, dec_one), 5)
    return (lambda w, v: enc(w, v.items())), (lambda r: dict(dec(r)))


def _field(annotation: Any) -> tuple[Encode, Decode]:
    annotation = _plain(annotation)
    inner = _optional(annotation)
    if inner is not None:
        enc_one, dec_one = _field(inner)  # a number: X[<=1] is a count and the number

        def enc(w: Writer, v: Any) -> None:
            w.u32(0 if v is None else 1)
            if v is not None:
                enc_one(w, v)

        def dec(r: Reader) -> Any:
            n = r.count(1)
            if n > 1:
                raise ValueError(f"bounded sequence of {n} at byte {r.pos}, at most 1")
            return dec_one(r) if n else None
        return enc, dec
    origin = typing.get_origin(annotation)
    if origin is list:
        item = _item(annotation, 0)
        return _array(item) if item in DTYPES else _sequence(_field(item), 1)
    if origin is dict:
        return _dict(_item(annotation, 1))
    if isinstance(annotation, type) and issubclass(annotation, BaseModel):
        return _codec(annotation)
    return _scalar(annotation)


def _header() -> tuple[Encode, Decode]:
    """A :class:`Header` as ``std_msgs/Header header`` and ``wavegrasp_msgs/Trace trace``."""
    i64 = _PRIM[int]

    def enc(w: Writer, h: Header) -> None:
        w.time(h.stamp_ns)
        w.string(h.frame_id)
        w.pad(8)
        w.buf.extend(i64.pack(h.seq))
        w.u32(len(h.trace))
        for hop in h.trace:
            w.string(hop.service)
            w.pad(8)
            w.buf.extend(i64.pack(hop.recv_ns))
            w.buf.extend(i64.pack(hop.sent_ns))

    def dec(r: Reader) -> dict[str, Any]:
        sec, nanosec = r.time()
        frame_id = r.string()
        seq = i64.unpack_from(r.data, r.take(8, 8))[0]
        hops = []
        for _ in range(r.count(21)):
            service = r.string()
            recv_ns, sent_ns = struct.unpack_from("<qq", r.data, r.take(16, 8))
            hops.append({"service": service, "recv_ns": recv_ns, "sent_ns": sent_ns})
        return {"seq": seq, "stamp_ns": sec * NS + nanosec, "frame_id": frame_id,
                "trace": hops}
    return enc, dec


@cache
def _codec(model: type[BaseModel]) -> tuple[Encode, Decode]:
    """The writer and reader of ``model``'s fields, in order (a dict for pydantic)."""
    parts = [(name, _header() if field.annotation is Header else _field(field.annotation))
             for name, field in model.model_fields.items()]

    def enc(w: Writer, msg: BaseModel) -> None:
        for name, (enc_field, _dec) in parts:
            enc_field(w, getattr(msg, name))

    def dec(r: Reader) -> dict[str, Any]:
        return {name: dec_field(r) for name, (_enc, dec_field) in parts}
    return enc, dec


def encode(msg: BaseModel) -> bytes:
    """``msg`` as CDR of its ``wavegrasp_msgs`` type, with the encapsulation header."""
    w = Writer()
    try:
        _codec(type(msg))[0](w, msg)
    except struct.error as exc:  # a number its CDR type cannot hold
        raise ValueError(f"{type(msg).__name__}: {exc}") from None
    return bytes(w.buf)


def decode(data: bytes | memoryview, model: type[BaseModel]) -> dict[str, Any]:
    """The fields of ``model`` read from its CDR ``data``, for ``model.model_validate``;
    raises ValueError naming what is malformed."""
    try:
        return _codec(model)[1](Reader(data))
    except (struct.error, UnicodeDecodeError, IndexError) as exc:
        raise ValueError(str(exc)) from None


def compile_all() -> None:
    """Compile every message type's codec (a service's first message then costs no more)."""
    for model in MESSAGE_TYPES.values():
        _codec(model)

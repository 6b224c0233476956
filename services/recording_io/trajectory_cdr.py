"""``trajectory_msgs/msg/JointTrajectory`` to and from CDR bytes, written out by hand.

rosbags builds one Python object per point of a trajectory: a plan's path of some 250 points
took 1.4 ms to encode and 2.2 ms to decode, and in closed-loop execution the gate sends one
for each of the planner's updates (several a second) to the arm, the planner and the recorder.
This writes and reads the points straight from and into numpy arrays, byte for byte what
rosbags writes (little-endian CDR, XCDR1; a test compares them).

Layout, offsets from the end of the 4-byte encapsulation header: ``std_msgs/Header`` (stamp
int32 sec, uint32 nanosec; frame_id string), ``string[] joint_names``, then the points, each
four ``float64[]`` (positions, velocities, accelerations, effort: a uint32 count, the values
aligned to 8 when there are any) and a ``builtin_interfaces/Duration`` time_from_start.
Strings are a uint32 length (with the NUL), the bytes and the NUL; every count and length is
aligned to 4.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass

import numpy as np

JOINT_TRAJECTORY = "trajectory_msgs/msg/JointTrajectory"
ENCAPSULATION = b"\x00\x01\x00\x00"  # CDR, little-endian
NS = 1_000_000_000
_U32, _TIME = struct.Struct("<I"), struct.Struct("<iI")


class _Writer:
    def __init__(self) -> None:
        self.buf = bytearray(ENCAPSULATION)

    def align(self, n: int) -> None:
        self.buf.extend(bytes(-(len(self.buf) - 4) % n))

    def u32(self, value: int) -> None:
        self.align(4)
        self.buf.extend(_U32.pack(value))

    def time(self, ns: int) -> None:
        self.align(4)
        self.buf.extend(_TIME.pack(ns // NS, ns % NS))

    def string(self, text: str) -> None:
        data = text.encode()
        self.u32(len(data) + 1)
        self.buf.extend(data + b"\0")

    def doubles(self, values: np.ndarray) -> None:
        self.u32(len(values))
        if len(values):
            self.align(8)
            self.buf.extend(np.ascontiguousarray(values, dtype="<f8").tobytes())


def encode_joint_trajectory(names: list[str], times_s: np.ndarray, q: np.ndarray,
                            qd: np.ndarray, frame_id: str = "") -> bytes:
    """A ``trajectory_msgs/msg/JointTrajectory`` as CDR bytes, as a ros2_control joint
    trajectory controller takes it: ``header.stamp`` the first sample's time, each point's
    ``time_from_start`` from it; no accelerations or efforts.

    times_s : array, shape (k,), seconds (the recording clock; a live vehicle's is the wall);
    q, qd : arrays, shape (k, n), rad or m and their rates, per joint of ``names``.
    """
    times_ns = np.round(np.asarray(times_s, dtype=float) * 1e9).astype(np.int64)
    start = int(times_ns[0]) if len(times_ns) else 0
    if start < 0 or (len(times_ns) and int(times_ns[-1]) - start >= 2**31 * NS):
        raise ValueError(f"joint_trajectory times {times_s[0]}..{times_s[-1]} s do not fit "
                         "a header stamp and int32 durations")
    w = _Writer()
    w.time(start)
    w.string(frame_id)
    w.u32(len(names))
    for name in names:
        w.string(name)
    w.u32(len(times_ns))
    empty = np.zeros(0)
    for k, t_ns in enumerate(times_ns):
        for values in (q[k], qd[k], empty, empty):
            w.doubles(values)
        w.time(int(t_ns) - start)
    return bytes(w.buf)


@dataclass
class Trajectory:
    """A JointTrajectory as read, unchecked: stamp_ns, frame_id, names, and per point its
    time_from_start (ns) and positions and velocities (each an array of any length)."""

    stamp_ns: int
    frame_id: str
    names: list[str]
    from_start_ns: list[int]
    positions: list[np.ndarray]
    velocities: list[np.ndarray]


class _Reader:
    def __init__(self, data: bytes | memoryview) -> None:
        self.data, self.pos = memoryview(data), 4
        if bytes(self.data[:4]) != ENCAPSULATION:
            raise ValueError("not little-endian CDR (encapsulation header "
                             f"{bytes(self.data[:4]).hex()})")

    def need(self, n: int) -> None:
        if self.pos + n > len(self.data):
            raise ValueError(f"ends at byte {len(self.data)}, {n} more needed at {self.pos}")

    def align(self, n: int) -> None:
        self.pos += -(self.pos - 4) % n

    def u32(self) -> int:
        self.align(4)
        self.need(4)
        (value,) = _U32.unpack_from(self.data, self.pos)
        self.pos += 4
        return value

    def time(self) -> tuple[int, int]:
        self.align(4)
        self.need(8)
        sec, nsec = _TIME.unpack_from(self.data, self.pos)
        self.pos += 8
        return sec, nsec

    def string(self) -> str:
        n = self.u32()
        self.need(n)
        raw = bytes(self.data[self.pos:self.pos + n])
        self.pos += n
        if n < 1 or raw[-1] != 0:
            raise ValueError(f"string without its terminator at byte {self.pos}")
        return raw[:-1].decode()

    def doubles(self) -> np.ndarray:
        n = self.u32()
        if not n:
            return np.zeros(0)
        self.align(8)
        self.need(8 * n)
        values = np.frombuffer(self.data, "<f8", n, self.pos)
        self.pos += 8 * n
        return values


def parse_joint_trajectory(cdr: bytes | memoryview) -> Trajectory:
    """Read a JointTrajectory's CDR, checking only its structure; raises ValueError naming
    what is malformed."""
    try:
        r = _Reader(cdr)
        sec, nsec = r.time()
        frame_id = r.string()
        count = r.u32()
        r.need(4 * count)  # each name at least its length
        names = [r.string() for _ in range(count)]
        count = r.u32()
        r.need(count * 24)  # each point at least its four counts and its duration
        from_start, positions, velocities = [], [], []
        for _ in range(count):
            positions.append(r.doubles())
            velocities.append(r.doubles())
            r.doubles()
            r.doubles()
            d_sec, d_nsec = r.time()
            from_start.append(d_sec * NS + d_nsec)
    except (ValueError, UnicodeDecodeError) as exc:
        raise ValueError(f"not a valid {JOINT_TRAJECTORY}: {exc}") from None
    return Trajectory(sec * NS + nsec, frame_id, names, from_start, positions, velocities)


def decode_joint_trajectory(cdr: bytes | memoryview
                            ) -> tuple[list[str], np.ndarray, np.ndarray, np.ndarray]:
    """A ``trajectory_msgs/msg/JointTrajectory``: (names, times (k,) s from its stamp's
    clock, positions (k, n), velocities (k, n), zero where a point has none). A stamp of 0
    means "now", as for a joint trajectory controller: times are then from 0. Raises
    ValueError naming the field that does not fit."""
    msg = parse_joint_trajectory(cdr)
    n, k = len(msg.names), len(msg.from_start_ns)
    if not k:
        raise ValueError("joint_trajectory: no points")
    q, qd = np.empty((k, n)), np.zeros((k, n))
    for i, (p, v) in enumerate(zip(msg.positions, msg.velocities, strict=True)):
        if len(p) != n or len(v) not in (0, n):
            raise ValueError(f"joint_trajectory: point {i} has {len(p)} positions and {len(v)} "
                             f"velocities for {n} joints")
        q[i] = p
        if len(v):
            qd[i] = v
    times = (msg.stamp_ns + np.array(msg.from_start_ns, dtype=np.int64)) * 1e-9
    if np.any(np.diff(times) <= 0):
        raise ValueError("joint_trajectory: time_from_start must increase strictly")
    if not (np.isfinite(q).all() and np.isfinite(qd).all()):
        raise ValueError("joint_trajectory: a position or velocity is not finite")
    return msg.names, times, q, qd

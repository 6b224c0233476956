"""The arm's ROS 2 messages to and from CDR bytes, written out by hand:
``trajectory_msgs/msg/JointTrajectory`` and ``sensor_msgs/msg/JointState``.

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

from dataclasses import dataclass

import numpy as np

from wavegrasp.schemas.cdr import NS, Reader, Writer

JOINT_TRAJECTORY = "trajectory_msgs/msg/JointTrajectory"
JOINT_STATE = "sensor_msgs/msg/JointState"


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
    w = Writer()
    w.time(start)
    w.string(frame_id)
    w.u32(len(names))
    for name in names:
        w.string(name)
    w.u32(len(times_ns))
    empty, k = np.zeros(0), 0
    for k, t_ns in enumerate(times_ns):
        if k and (len(w.buf) - 4) % 8 == 0 and q.shape[1]:  # the rest alike: at once
            w.buf.extend(_points(q[k:], qd[k:], times_ns[k:] - start).tobytes())
            break
        for values in (q[k], qd[k], empty, empty):
            w.doubles(values)
        w.time(int(t_ns) - start)
    return bytes(w.buf)


def _layout(n: int) -> np.dtype:
    """A point of n positions and n velocities (n > 0) that starts 8-aligned, as CDR lays it
    out (and so ends 8-aligned: every point after the first is one of these)."""
    return np.dtype([("n_q", "<u4"), ("pad_q", "V4"), ("q", "<f8", (n,)), ("n_qd", "<u4"),
                     ("pad_qd", "V4"), ("qd", "<f8", (n,)), ("empty", "<u4", (2,)),
                     ("sec", "<i4"), ("nanosec", "<u4")])


def _points(q: np.ndarray, qd: np.ndarray, from_start_ns: np.ndarray) -> np.ndarray:
    points = np.zeros(len(q), _layout(q.shape[1]))
    points["n_q"] = points["n_qd"] = q.shape[1]
    points["q"], points["qd"] = q, qd
    points["sec"], points["nanosec"] = np.divmod(from_start_ns, NS)
    return points


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


def _read_alike(r: Reader, rest: int, positions: list, velocities: list,
                from_start: list) -> bool:
    """Read the ``rest`` points at once if they are laid out as the first was (n positions
    and n velocities, no accelerations or efforts, 8-aligned); False, having read nothing, if
    not."""
    n = len(positions[0])
    if not n or len(velocities[0]) != n or (r.pos - 4) % 8:
        return False
    layout = _layout(n)
    if r.pos + rest * layout.itemsize > r.end:
        return False
    points = np.frombuffer(r.data, layout, rest, r.pos)
    if not ((points["n_q"] == n).all() and (points["n_qd"] == n).all()
            and not points["empty"].any()):
        return False
    r.pos += rest * layout.itemsize
    positions.extend(points["q"])
    velocities.extend(points["qd"])
    from_start.extend((points["sec"].astype(np.int64) * NS + points["nanosec"]).tolist())
    return True


def parse_joint_trajectory(cdr: bytes | memoryview) -> Trajectory:
    """Read a JointTrajectory's CDR, checking only its structure; raises ValueError naming
    what is malformed."""
    try:
        r = Reader(cdr)
        sec, nsec = r.time()
        frame_id = r.string()
        count = r.u32()
        r.need(4 * count)  # each name at least its length
        names = [r.string() for _ in range(count)]
        count = r.u32()
        r.need(count * 24)  # each point at least its four counts and its duration
        from_start, positions, velocities = [], [], []
        for k in range(count):
            if k and _read_alike(r, count - k, positions, velocities, from_start):
                break
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
    (a joint trajectory controller's "start now") gives times from 0: the commander always
    stamps its trajectories, and the sim follows them as stamped. Raises ValueError naming
    the field that does not fit."""
    msg = parse_joint_trajectory(cdr)
    n, k = len(msg.names), len(msg.from_start_ns)
    if not k:
        raise ValueError("joint_trajectory: no points")
    for i, (p, v) in enumerate(zip(msg.positions, msg.velocities, strict=True)):
        if len(p) != n or len(v) not in (0, n):
            raise ValueError(f"joint_trajectory: point {i} has {len(p)} positions and {len(v)} "
                             f"velocities for {n} joints")
    q = np.array(msg.positions, dtype=float).reshape(k, n)
    qd = np.array([v if len(v) else np.zeros(n) for v in msg.velocities],
                  dtype=float).reshape(k, n)
    times = (msg.stamp_ns + np.array(msg.from_start_ns, dtype=np.int64)) * 1e-9
    if np.any(np.diff(times) <= 0):
        raise ValueError("joint_trajectory: time_from_start must increase strictly")
    if not (np.isfinite(q).all() and np.isfinite(qd).all()):
        raise ValueError("joint_trajectory: a position or velocity is not finite")
    return msg.names, times, q, qd


def encode_joint_state(stamp_ns: int, names: list[str], positions: np.ndarray,
                       velocities: np.ndarray) -> bytes:
    """A ``sensor_msgs/msg/JointState`` as CDR bytes, as ros2_control's joint state
    broadcaster publishes one: positions (n,) and velocities (n,), radians (revolute) or
    metres (prismatic), per joint of ``names``; no efforts."""
    p, v = np.asarray(positions, dtype=float), np.asarray(velocities, dtype=float)
    if p.shape != (len(names),) or v.shape != (len(names),):
        raise ValueError(f"joint state of {len(names)} joints needs that many positions and "
                         f"velocities, got shapes {p.shape} and {v.shape}")
    if stamp_ns < 0 or stamp_ns >= 2**31 * NS:
        raise ValueError(f"stamp {stamp_ns} ns does not fit a header stamp")
    w = Writer()
    w.time(stamp_ns)
    w.string("")
    w.u32(len(names))
    for name in names:
        w.string(name)
    for values in (p, v, np.zeros(0)):
        w.doubles(values)
    return bytes(w.buf)


def parse_joint_state(cdr: bytes | memoryview
                      ) -> tuple[int, list[str], np.ndarray, np.ndarray, np.ndarray]:
    """Read a JointState's CDR, checking only its structure: (stamp ns, names, positions,
    velocities, efforts); raises ValueError naming what is malformed."""
    try:
        r = Reader(cdr)
        sec, nsec = r.time()
        r.string()
        count = r.u32()
        r.need(4 * count)
        names = [r.string() for _ in range(count)]
        arrays = [r.doubles() for _ in range(3)]
    except (ValueError, UnicodeDecodeError) as exc:
        raise ValueError(f"not a valid {JOINT_STATE}: {exc}") from None
    return sec * NS + nsec, names, *arrays


def decode_joint_state(cdr: bytes | memoryview) -> tuple[int, list[str], np.ndarray, np.ndarray]:
    """A ``sensor_msgs/msg/JointState``: (stamp ns, names, positions (n,), velocities (n,),
    zero where it has none); raises ValueError naming the field that does not fit."""
    stamp_ns, names, p, v, _effort = parse_joint_state(cdr)
    n = len(names)
    if len(p) != n:
        raise ValueError(f"joint_states: {n} names but {len(p)} positions")
    if len(v) not in (0, n):
        raise ValueError(f"joint_states: {n} names but {len(v)} velocities")
    v = v if len(v) else np.zeros(n)
    if not (np.isfinite(p).all() and np.isfinite(v).all()):
        raise ValueError("joint_states: a position or velocity is not finite")
    return stamp_ns, names, np.array(p), np.array(v)

"""Zenoh hop latency between two processes through a real ``wavegrasp router``.

Run::

    python -m wavegrasp.ops.bench_zenoh_hop [--count N] [--points 30000] [--warmup 50]

The script starts a router (``wavegrasp router`` on a free port) and an echo process (this
script with ``--echo``), both clients of the router as deployed: client -> router -> client.
Both sides use the project's :class:`~wavegrasp.runtime.bus.Bus`, so the whole stack is
measured (a model to CDR and back or raw CDR, zenoh callback, inbox queue, service loop,
dispatch).

Ping-pong, one message in flight: this process publishes a ping, the echo process's loop
republishes it on a pong key at once (an observation: decoded and re-published with a trace
hop, like a service does; a cloud: the same bytes via ``publish_cdr``), and this process's
loop handles the pong.

* hop = round trip / 2, timed with ``perf_counter_ns`` from before ``publish`` to the pong's
  handler on this loop: publish call -> handler in the other process, as a service sees it.
* direct = echo's ``Delivery.recv_ns`` (wall clock, zenoh callback thread) minus the sender's
  ``time.time_ns()`` carried in the message (an observation: ``header.trace[-1].sent_ns``, by
  ``Bus.publish``; a cloud: the attachment's ``source_ns``, by ``Bus.publish_cdr``). It
  excludes the receiver's inbox queue, loop wake-up and decode. Valid because both processes
  share one wall clock.

Messages: (a) an ObjectObservation (CDR, ~300 bytes), ``--count`` (default 1000) times;
(b) a PointCloud2 of ``--points`` x,y,z float32 points (CDR), ``--count`` (default 300) times;
each after ``--warmup`` messages that are not counted.
"""

from __future__ import annotations

import argparse
import contextlib
import logging
import os
import queue
import signal
import socket
import subprocess
import sys
import time
import uuid
from collections.abc import Callable

import numpy as np
from pydantic import BaseModel

from wavegrasp.runtime.bus import Bus, Delivery
from wavegrasp.runtime.settings import Settings
from wavegrasp.runtime.trace import CdrAttachment, derived_header, new_header
from wavegrasp.schemas import ObjectObservation, Vec3
from wavegrasp.schemas.ros import to_cdr

CLOUD_TYPE = "sensor_msgs/msg/PointCloud2"
ECHO = "bench-echo"
#: The handshake's pings count up from here, clear of the measured ones (sequence numbers
#: are never negative).
HANDSHAKE_SEQ = 1_000_000_000


class EchoReport(BaseModel):
    """The echo's direct one-way latencies, ns, by ping sequence number."""

    small: dict[int, int]
    cloud: dict[int, int]


class Done(BaseModel):
    """Ask the echo for its report and to exit."""


def keys(run: str) -> dict[str, str]:
    base = f"wavegrasp/bench/{run}"
    names = ("small/ping", "small/pong", "cloud/ping", "cloud/pong", "done", "report")
    return {n: f"{base}/{n}" for n in names}


def open_bus(name: str, endpoint: str) -> Bus:
    return Bus(Settings.from_env(name, env={"ZENOH_CONNECT": endpoint}))


# -- echo process -----------------------------------------------------------------------------
def echo(endpoint: str, run: str, parent: int) -> int:
    """Republish every ping as a pong from this loop; report direct one-way times at the end."""
    k = keys(run)
    bus = open_bus(ECHO, endpoint)
    report = EchoReport(small={}, cloud={})
    finished = False

    def on_small(msg: ObjectObservation, d: Delivery) -> None:
        report.small[msg.header.seq] = d.recv_ns - msg.header.trace[-1].sent_ns
        out = msg.model_copy(update={"header": derived_header(msg.header, ECHO, d.recv_ns)})
        bus.publish(k["small/pong"], out)

    def on_cloud(d: Delivery) -> None:
        bus.publish_cdr(k["cloud/pong"], d.payload, CLOUD_TYPE)
        att = CdrAttachment.decode(d.attachment)
        if att is not None:
            report.cloud[att.seq] = d.recv_ns - att.source_ns

    def on_done(_msg: Done, _d: Delivery) -> None:
        nonlocal finished
        bus.publish(k["report"], report)
        finished = True

    try:
        bus.subscribe(k["cloud/ping"], on_cloud)
        bus.subscribe(k["done"], on_done, Done)
        bus.subscribe(k["small/ping"], on_small, ObjectObservation)
        bus.declare_alive()
        while not finished and os.getppid() == parent:
            with contextlib.suppress(queue.Empty):
                bus.dispatch(bus.inbox.get(timeout=0.5))
        time.sleep(0.2)  # let the report leave before the session closes
    finally:
        bus.close()
    return 0


# -- benchmark process ------------------------------------------------------------------------
def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def spawn(args: list[str]) -> subprocess.Popen[bytes]:
    """Start a child in its own process group, so stopping it reaches all of it."""
    return subprocess.Popen(args, start_new_session=True,
                            env={**os.environ, "PYTHONUNBUFFERED": "1",
                                 "WAVEGRASP_LOG_LEVEL": "WARNING"})


def stop(proc: subprocess.Popen[bytes] | None) -> None:
    if proc is None or proc.poll() is not None:
        return
    try:
        os.killpg(proc.pid, signal.SIGTERM)
        proc.wait(5)
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, signal.SIGKILL)
        proc.wait()
    except ProcessLookupError:
        pass


def start_router() -> tuple[subprocess.Popen[bytes], str]:
    """A ``wavegrasp router`` listening on a free local port; returns it and its endpoint."""
    for _ in range(3):
        port = free_port()
        endpoint = f"tcp/127.0.0.1:{port}"
        proc = spawn([sys.executable, "-m", "wavegrasp", "router", "--listen", endpoint])
        deadline = time.monotonic() + 15
        while proc.poll() is None and time.monotonic() < deadline:
            with socket.socket() as s:
                if s.connect_ex(("127.0.0.1", port)) == 0:
                    return proc, endpoint
            time.sleep(0.05)
        stop(proc)
    raise RuntimeError("wavegrasp router did not start listening")


def point_cloud_cdr(n: int) -> bytes:
    """A CDR PointCloud2 of ``n`` random x,y,z float32 points, as the recordings hold them."""
    from wavegrasp.recording_io.typestore import ros2_typestore
    from wavegrasp.recording_io.writer import FLOAT32, check_points

    pts = check_points(np.random.default_rng(0).uniform(-1, 1, (n, 3)))
    store = ros2_typestore()
    t = store.types
    header = t["std_msgs/msg/Header"](
        stamp=t["builtin_interfaces/msg/Time"](sec=1, nanosec=0), frame_id="trisect_optical")
    fields = [t["sensor_msgs/msg/PointField"](name=c, offset=4 * i, datatype=FLOAT32, count=1)
              for i, c in enumerate("xyz")]
    msg = t[CLOUD_TYPE](header=header, height=1, width=n, fields=fields, is_bigendian=False,
                        point_step=12, row_step=12 * n, data=pts.view(np.uint8).reshape(-1),
                        is_dense=True)
    return bytes(store.serialize_cdr(msg, CLOUD_TYPE))


def observation(seq: int) -> ObjectObservation:
    return ObjectObservation(
        header=new_header("bench", seq, time.time_ns()), centroid=Vec3(x=0.25, y=-0.5, z=1.0),
        points_used=2500, quality=0.9, sigma_m=0.002)


class Pinger:
    """This side's bus and the pong it is waiting for."""

    def __init__(self, bus: Bus, k: dict[str, str], echo_proc: subprocess.Popen[bytes]) -> None:
        self.bus, self.k, self.echo_proc = bus, k, echo_proc
        self.got: tuple[str, int] | None = None
        self.report: EchoReport | None = None
        bus.subscribe(k["small/pong"], lambda m, d: self._got("small", m.header.seq),
                      ObjectObservation)
        bus.subscribe(k["cloud/pong"], self._on_cloud)
        bus.subscribe(k["report"], lambda m, d: setattr(self, "report", m), EchoReport)

    def _got(self, kind: str, seq: int) -> None:
        self.got = (kind, seq)

    def _on_cloud(self, d: Delivery) -> None:
        att = CdrAttachment.decode(d.attachment)
        self._got("cloud", -1 if att is None else att.seq)

    def wait_for(self, done: Callable[[], bool], timeout_s: float) -> bool:
        """Run this loop until ``done()`` or ``timeout_s``; False on timeout."""
        deadline = time.monotonic() + timeout_s
        while not done():
            left = deadline - time.monotonic()
            if left <= 0:
                return False
            try:
                self.bus.dispatch(self.bus.inbox.get(timeout=left))
            except queue.Empty:
                return False
        return True

    def handshake(self, timeout_s: float = 30.0) -> None:
        """Ping (seq from HANDSHAKE_SEQ, not counted) until the echo answers: every route is
        up."""
        deadline = time.monotonic() + timeout_s
        seq = HANDSHAKE_SEQ
        while time.monotonic() < deadline:
            if self.echo_proc.poll() is not None:
                raise RuntimeError(f"echo process exited with {self.echo_proc.returncode}")
            self.bus.publish(self.k["small/ping"], observation(seq))
            if self.wait_for(lambda s=seq: self.got == ("small", s), 0.5):
                return
            seq += 1
        raise RuntimeError("no answer from the echo process")

    def small(self, seq: int, pause_s: float = 0.0) -> int:
        """One observation's round trip, ns, after ``pause_s`` of idleness."""
        time.sleep(pause_s)
        msg = observation(seq)
        t0 = time.perf_counter_ns()
        self.bus.publish(self.k["small/ping"], msg)
        if not self.wait_for(lambda: self.got == ("small", seq), 5.0):
            raise RuntimeError(f"no pong for small ping {seq}")
        return time.perf_counter_ns() - t0

    def cloud(self, cdr: bytes, expect: int, pause_s: float = 0.0) -> int:
        """One CDR round trip, ns, after ``pause_s`` of idleness; ``expect`` is the ping's
        sequence number (one per ping)."""
        time.sleep(pause_s)
        t0 = time.perf_counter_ns()
        seq = self.bus.publish_cdr(self.k["cloud/ping"], cdr, CLOUD_TYPE)
        if seq != expect or not self.wait_for(lambda: self.got == ("cloud", seq), 5.0):
            raise RuntimeError(f"no pong for cloud ping {seq}")
        return time.perf_counter_ns() - t0


def run(args: argparse.Namespace) -> list[tuple[str, int, np.ndarray, np.ndarray]]:
    """Run both benchmarks; returns (message, bytes, one-way hops ns, direct one-way ns)."""
    n_small = args.count if args.count is not None else 1000
    n_cloud = args.count if args.count is not None else 300
    run_id = uuid.uuid4().hex[:8]
    k = keys(run_id)
    cdr = point_cloud_cdr(args.points)
    router = echo_proc = None
    bus = None
    try:
        router, endpoint = start_router()
        echo_proc = spawn([sys.executable, "-m", "wavegrasp.ops.bench_zenoh_hop", "--echo",
                           "--connect", endpoint, "--run-id", run_id,
                           "--parent", str(os.getpid())])
        bus = open_bus("bench", endpoint)
        p = Pinger(bus, k, echo_proc)
        p.handshake()
        w = args.warmup
        pause = args.interval_ms / 1e3
        small = np.array([p.small(i, pause) for i in range(w + n_small)][w:]) / 2
        cloud = np.array([p.cloud(cdr, i, pause) for i in range(w + n_cloud)][w:]) / 2
        bus.publish(k["done"], Done())
        if not p.wait_for(lambda: p.report is not None, 10.0) or p.report is None:
            raise RuntimeError("no report from the echo process")
        rep = p.report
        d_small = np.array([rep.small[i] for i in range(w, w + n_small)])
        d_cloud = np.array([rep.cloud[i] for i in range(w, w + n_cloud)])
        size = len(to_cdr(observation(0)))
        return [("ObjectObservation (CDR)", size, small, d_small),
                (f"PointCloud2 {args.points} pts (CDR)", len(cdr), cloud, d_cloud)]
    finally:
        if bus is not None:
            bus.close()
        stop(echo_proc)
        stop(router)


def print_table(rows: list[tuple[str, int, np.ndarray, np.ndarray]]) -> None:
    print("one-way latency, ms; hop = RTT/2 (perf_counter), direct = echo recv_ns - send time_ns")
    head = ("message", "bytes", "count", "hop p50", "hop p99", "hop max", "dir p50", "dir p99")
    fmt = "{:<32} {:>7} {:>5} {:>8} {:>8} {:>8} {:>8} {:>8}"
    print(fmt.format(*head))
    for name, size, hop, direct in rows:
        ms = [f"{v / 1e6:.3f}" for v in (*np.percentile(hop, [50, 99]), hop.max(),
                                         *np.percentile(direct, [50, 99]))]
        print(fmt.format(name, size, len(hop), *ms))


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--count", type=int, help="messages measured (default 1000 / 300 cloud)")
    parser.add_argument("--points", type=int, default=30000, help="points per cloud")
    parser.add_argument("--warmup", type=int, default=50, help="messages sent before measuring")
    parser.add_argument("--interval-ms", type=float, default=0.0,
                        help="idle time before each ping (100: a 10 Hz camera's pace; 0: "
                        "back to back)")
    parser.add_argument("--echo", action="store_true", help=argparse.SUPPRESS)
    parser.add_argument("--connect", help=argparse.SUPPRESS)
    parser.add_argument("--run-id", help=argparse.SUPPRESS)
    parser.add_argument("--parent", type=int, default=0, help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    logging.basicConfig(level="WARNING", format="%(levelname)s %(name)s: %(message)s")
    if args.echo:
        signal.signal(signal.SIGTERM, lambda *_: sys.exit(0))
        return echo(args.connect, args.run_id, args.parent)
    signal.signal(signal.SIGTERM, lambda *_: sys.exit(143))  # unwind so children are stopped
    try:
        print_table(run(args))
    except KeyboardInterrupt:
        return 130
    except RuntimeError as exc:
        print(f"bench_zenoh_hop: {exc}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())

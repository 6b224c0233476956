"""The service skeleton every ``wavegrasp <service>`` shares: bus, loop, health, stats, signals.

A service subclasses :class:`Service`, subscribes in ``__init__`` and does its work in handlers
and ``on_tick``; all of them run on one thread, the service loop, so they need no locks. Tests
can call handlers directly or run the loop over a real zenoh session.
"""

from __future__ import annotations

import argparse
import faulthandler
import gc
import logging
import queue
import signal
import sys
import threading
import time
from collections import Counter

from wavegrasp.runtime.bus import Bus, Delivery
from wavegrasp.runtime.clock import RecordingClock
from wavegrasp.runtime.heartbeat import Heartbeat
from wavegrasp.runtime.settings import Settings
from wavegrasp.runtime.trace import derived_header, new_header
from wavegrasp.schemas import (
    CLOCK_KEY,
    Clock,
    FrameAck,
    Header,
    ServiceStats,
    ack_key,
    stats_key,
)
from wavegrasp.schemas.ros import warm_up

log = logging.getLogger(__name__)
STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM)


def setup_logging(level: str = "INFO") -> None:
    """One line per record on stderr; the launcher prefixes each line with the service name."""
    logging.basicConfig(level=level.upper(), format="%(levelname)s %(name)s: %(message)s",
                        force=True)


def service_main(name: str, doc: str | None, settings_cls: type[Settings],
                 service_cls: type[Service], argv: list[str] | None) -> int:
    """``wavegrasp NAME``: a service without options of its own: its settings from the
    environment (a bad one: one line naming it, exit 2), its logging, its loop."""
    argparse.ArgumentParser(prog=f"wavegrasp {name}", description=doc,
                            formatter_class=argparse.RawDescriptionHelpFormatter
                            ).parse_args(argv)
    try:
        settings = settings_cls.from_env(name)
        setup_logging(settings.log_level)
        service = service_cls(settings)
    except ValueError as exc:
        print(f"wavegrasp {name}: {exc}", file=sys.stderr)
        return 2
    return service.run()


def freeze_startup_objects() -> None:
    """Leave what start-up made (modules, models: about 115 000 objects) out of the garbage
    collector's full passes from now on: walking them took about 50 ms each time, a frame's
    worth of latency whenever one fell on the camera-to-decision path."""
    gc.collect()
    gc.freeze()


class Service:
    """Base of all services. ``run()`` blocks until SIGINT/SIGTERM or :meth:`stop`.

    Frame acknowledgements chain along the pipeline: a service with ``ack_after`` set, once
    that upstream service has acknowledged camera frame N (so everything it sent for N has
    arrived: one session's messages arrive in order), finishes its own work for N
    (:meth:`finish_frame`) and acknowledges N on ``wavegrasp/<name>/ack``. The player's
    lockstep waits for the last service's acknowledgement.
    """

    tick_period_s = 0.05
    #: Whether the runtime subscribes to ``wavegrasp/clock`` for :attr:`clock`; a service
    #: whose own subscription covers it (the recorder's) feeds :meth:`on_clock` itself, so
    #: each tick is delivered once.
    subscribes_clock = True
    #: The upstream service whose frame acknowledgements this one follows (None: none).
    ack_after: str | None = None

    def __init__(self, settings: Settings, bus: Bus | None = None) -> None:
        self.settings = settings
        self.name = settings.service
        self.bus = bus if bus is not None else Bus(settings)
        self.clock = RecordingClock(wall=settings.clock == "wall")
        self.stopping = threading.Event()
        self.counters: Counter[str] = Counter()  # service-specific, published with the stats
        self.exit_code = 0
        self.heartbeat = Heartbeat(settings.health_file)
        self._started = time.monotonic()
        self._next_stats = 0.0
        self._stats_seq = 0
        if self.subscribes_clock:
            self.bus.subscribe(CLOCK_KEY, self.on_clock, Clock)
        if self.ack_after is not None:
            self.bus.subscribe(ack_key(self.ack_after), self.on_upstream_ack, FrameAck)

    def on_upstream_ack(self, msg: FrameAck, d: Delivery) -> None:
        self.finish_frame(msg.frame_seq)
        self.ack_frame(msg.header, d.recv_ns, msg.frame_seq)

    def finish_frame(self, frame_seq: int) -> None:
        """Called before acknowledging a frame: finish work deferred to ``on_tick``."""

    def ack_frame(self, source: Header, recv_ns: int, frame_seq: int) -> None:
        """Acknowledge camera frame ``frame_seq`` (everything for it has been published)."""
        self.bus.publish(ack_key(self.name), FrameAck(
            header=derived_header(source, self.name, recv_ns), service=self.name,
            frame_seq=frame_seq))

    def on_clock(self, msg: Clock, _delivery: object) -> None:
        self.clock.on_clock(msg)

    # hooks for subclasses
    def on_start(self) -> None:
        """Called on the loop before the first message, after the liveliness token is up."""

    def on_tick(self) -> None:
        """Called on the loop at least every ``tick_period_s``."""

    def on_stop(self) -> None:
        """Called on the loop after the inbox is drained, before the bus closes."""

    def stop(self, code: int = 0) -> None:
        self.exit_code = self.exit_code or code
        self.stopping.set()

    def publish_stats(self) -> None:
        b = self.bus
        self._stats_seq += 1
        self.bus.publish(stats_key(self.name), ServiceStats(
            header=new_header(self.name, self._stats_seq, self.clock.now_ns()),
            service=self.name, subscriptions=list(b.subscriptions), received=dict(b.received),
            received_shared=dict(b.received_shared), pool_full=dict(b.pool_full),
            bad=dict(b.bad), last_bad_reason=dict(b.last_bad_reason), counters=dict(self.counters),
            uptime_s=time.monotonic() - self._started, cpu_s=time.process_time()))

    def check_signals(self) -> None:
        """Stop on a pending SIGINT/SIGTERM (``wavegrasp <service>`` blocks them: see
        :meth:`handle_signals`)."""
        if signal.sigtimedwait(STOP_SIGNALS, 0) is not None:
            self.stopping.set()

    def drain(self, max_items: int | None = None) -> int:
        """Handle what is in the inbox now (at most ``max_items``); returns how many."""
        self.check_signals()
        n = 0
        while max_items is None or n < max_items:
            try:
                delivery = self.bus.inbox.get_nowait()
            except queue.Empty:
                break
            self.bus.dispatch(delivery)
            n += 1
        return n

    def step(self, timeout_s: float) -> None:
        """One turn of the loop: wait up to ``timeout_s`` for input, handle it, tick."""
        self.check_signals()
        try:
            delivery = self.bus.inbox.get(timeout=timeout_s)
            self.bus.dispatch(delivery)
            self.drain(max_items=256)
        except queue.Empty:
            pass
        self.on_tick()
        now = time.monotonic()
        if now >= self._next_stats:
            self._next_stats = now + self.settings.stats_period_s
            self.publish_stats()
        self.heartbeat.beat(self.bus)

    def serve(self) -> int:
        """The service's main loop; returns an exit code. Sources (the player) override it."""
        while not self.stopping.is_set():
            self.step(self.tick_period_s)
        return self.exit_code

    def handle_signals(self) -> None:
        """Install the SIGINT/SIGTERM handlers that stop the loop.

        ``wavegrasp <service>`` blocks these signals from the start and each turn of the loop
        takes a pending one (:meth:`step`): a handler alone was not enough (rarely, under
        load, a service ignored SIGTERM with its handler installed and the signal neither
        blocked nor pending). The handlers serve a service run some other way.
        """
        for sig in STOP_SIGNALS:
            signal.signal(sig, self._on_signal)

    def _on_signal(self, *_: object) -> None:
        self.stopping.set()

    def run(self) -> int:
        """Serve until stopped; returns the process exit code."""
        self.handle_signals()
        # SIGUSR1 prints every thread's stack: the launcher asks before it kills a stuck service.
        faulthandler.register(signal.SIGUSR1, all_threads=True)
        try:
            self.bus.declare_alive()
            warm_up()  # a no-op in a service forked from the launcher's server
            self.on_start()
            freeze_startup_objects()
            sys.setswitchinterval(self.settings.switch_interval_ms / 1e3)
            self.exit_code = self.serve()
            self.drain()
            self.on_stop()
            self.publish_stats()
        finally:
            self.bus.close()
        log.info("%s stopped (exit %d)", self.name, self.exit_code)
        return self.exit_code

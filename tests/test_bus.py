"""The typed bus over real zenoh sessions in separate processes."""

from __future__ import annotations

import queue
import signal
import sys
import time
from pathlib import Path

from wavegrasp.runtime.trace import CdrAttachment
from wavegrasp.schemas import Header, Hop, ObjectObservation, ServiceStats, Vec3, health_key

from conftest import Router, spawn, stop, wait_until

ECHO = str(Path(__file__).with_name("echo_node.py"))


def start_echo(router: Router, name: str = "echo"):
    proc = spawn([sys.executable, ECHO, name], router.env)
    return proc


def test_typed_round_trip_between_processes(router: Router) -> None:
    proc = start_echo(router)
    bus = router.bus()
    try:
        assert not bus.wait_for_services(["echo"], timeout_s=15)
        got: queue.SimpleQueue = queue.SimpleQueue()
        bus.subscribe("test/pong", lambda m, d: got.put(m), ObjectObservation)
        sent = ObjectObservation(
            header=Header(seq=42, stamp_ns=123_456_789, trace=[Hop(service="test", recv_ns=1)]),
            centroid=Vec3(x=0.25, y=-0.5, z=1.0), points_used=321, quality=0.75, sigma_m=0.002)
        deadline = time.monotonic() + 10
        reply = None
        while reply is None and time.monotonic() < deadline:
            bus.publish("test/ping", sent)
            try:
                bus.dispatch(bus.inbox.get(timeout=0.5))
                reply = got.get_nowait()
            except queue.Empty:
                pass
        assert reply is not None, "no reply from the echo process"
        assert reply.centroid == sent.centroid and reply.points_used == 321
        assert reply.header.seq == 42 and reply.header.stamp_ns == 123_456_789
        hops = reply.header.trace
        assert [h.service for h in hops] == ["test", "echo"]
        assert hops[0].sent_ns > 0, "the bus stamps the sender's hop"
        assert hops[0].sent_ns <= hops[1].recv_ns <= hops[1].sent_ns
    finally:
        bus.close()
        assert stop(proc) == 0


def test_garbage_is_counted_and_the_service_lives(router: Router) -> None:
    proc = start_echo(router)
    bus = router.bus()
    stats: dict[str, ServiceStats] = {}
    try:
        assert not bus.wait_for_services(["echo"], timeout_s=15)
        bus.subscribe("wavegrasp/echo/stats", lambda m, d: stats.update(last=m), ServiceStats)
        garbage = [b"\x00\xffnot json", b'{"header": 5}', b"[]", b'{"centroid": {"x": "a"}}']
        for payload in garbage:
            bus.publish_bytes("test/ping", payload)

        def counted() -> bool:
            while not bus.inbox.empty():
                bus.dispatch(bus.inbox.get())
            s = stats.get("last")
            return s is not None and s.bad.get("test/ping", 0) == len(garbage)

        assert wait_until(counted, timeout=10), stats
        assert "ObjectObservation" in stats["last"].last_bad_reason["test/ping"]
        assert proc.poll() is None
        assert not bus.wait_for_services(["echo"], timeout_s=5)
    finally:
        bus.close()
        stop(proc)


def test_liveliness_appears_and_disappears_on_kill(router: Router) -> None:
    bus = router.bus()
    events: queue.SimpleQueue = queue.SimpleQueue()
    sub = bus.session.liveliness().declare_subscriber(
        health_key("*"), lambda s: events.put((str(s.key_expr), str(s.kind))))
    proc = start_echo(router, "victim")
    try:
        assert not bus.wait_for_services(["victim"], timeout_s=15)
        time.sleep(0.2)
        stop(proc, signal.SIGKILL)
        assert wait_until(lambda: "victim" not in bus.alive_services(0.5), timeout=10)
        seen = []
        while not events.empty():
            seen.append(events.get())
        assert (health_key("victim"), "SampleKind.PUT") in seen
        assert (health_key("victim"), "SampleKind.DELETE") in seen
    finally:
        sub.undeclare()
        bus.close()
        stop(proc)


def test_attachment_round_trip_and_plain_rmw_layout() -> None:
    att = CdrAttachment(seq=7, source_ns=10**18, gid=bytes(range(16)), log_time_ns=5)
    assert CdrAttachment.decode(att.encode()) == att
    plain = att.encode()[:-8]  # rmw_zenoh's layout without our log time
    assert CdrAttachment.decode(plain) == CdrAttachment(7, 10**18, bytes(range(16)), 0)


def test_own_keys_arrive_in_the_order_they_were_sent(router: Router) -> None:
    """A big message on one key then a small one on another (a plan, then the frame's
    acknowledgement) reach the inbox in that order: zenoh runs different subscribers'
    callbacks concurrently, so the bus serves all wavegrasp/ keys from one subscriber."""
    sender, receiver = router.bus(), router.bus()
    try:
        receiver.subscribe("wavegrasp/test/plan", lambda d: None)
        receiver.subscribe("wavegrasp/test/ack", lambda d: None)
        receiver.subscribe("wavegrasp/*/other", lambda d: None)
        time.sleep(1.0)
        big = b"p" * 20_000
        order = []
        for _ in range(100):
            sender.publish_bytes("wavegrasp/test/plan", big)
            sender.publish_bytes("wavegrasp/test/ack", b"{}")
            order += [receiver.inbox.get(timeout=5).key, receiver.inbox.get(timeout=5).key]
        assert order == ["wavegrasp/test/plan", "wavegrasp/test/ack"] * 100
        sender.publish_bytes("wavegrasp/test/unsubscribed", b"{}")  # dropped, not queued
        sender.publish_bytes("wavegrasp/x/other", b"{}")
        assert receiver.inbox.get(timeout=5).key == "wavegrasp/x/other"
    finally:
        sender.close()
        receiver.close()

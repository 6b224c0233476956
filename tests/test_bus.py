"""The typed bus over real zenoh sessions in separate processes."""

from __future__ import annotations

import contextlib
import fcntl
import os
import queue
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import zenoh
from pydantic import BaseModel

from wavegrasp.runtime.bus import decode_model, memory_lock_limit, remove_orphaned_segments
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


def test_our_messages_go_as_cdr_and_a_tools_own_models_as_json(router: Router) -> None:
    class Note(BaseModel):  # not one of our messages
        text: str

    sender, receiver = router.bus("sender"), router.bus("receiver")
    try:
        receiver.subscribe("test/**", lambda d: None)
        time.sleep(0.5)
        obs = ObjectObservation(header=Header(seq=3, stamp_ns=5), points_used=2)
        sender.publish("test/obs", obs)
        sender.publish("test/note", Note(text="hello"))
        got = {d.key: d for d in (receiver.inbox.get(timeout=5) for _ in range(2))}
        assert got["test/obs"].encoding == "application/cdr;wavegrasp_msgs/msg/ObjectObservation"
        assert decode_model(got["test/obs"], ObjectObservation).points_used == 2
        assert got["test/note"].encoding == "application/json;Note"
        assert Note.model_validate_json(got["test/note"].payload).text == "hello"
    finally:
        sender.close()
        receiver.close()


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


def test_a_restart_shows_while_the_dead_process_token_lingers(router: Router) -> None:
    """A router passes on one token per key: a service's successor that declares its token
    before the router has dropped its predecessor's shows no new service token; its own
    process token does, and that is when it counts as back."""
    watcher = router.bus()
    watcher.watch_alive()
    old = router.bus("victim")
    new = None
    try:
        old.declare_alive()
        assert wait_until(lambda: "victim" in watcher.alive_now(), timeout=10)
        first = watcher.alive_since["victim"]
        restarted = time.monotonic()
        new = router.bus("victim")
        new.declare_alive()  # while the old process's token still stands
        assert wait_until(lambda: watcher.alive_since["victim"] >= restarted, timeout=10), \
            "the second process of a service was never seen"
        assert first < restarted
        old.close()
        time.sleep(0.5)
        assert "victim" in watcher.alive_now(), "the successor's service token still stands"
    finally:
        for bus in (new, old, watcher):
            if bus is not None:
                bus.close()


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


def test_large_payloads_cross_through_shared_memory_unless_it_is_off(router: Router) -> None:
    """A camera-sized cloud reaches a subscriber on this host through zenoh's shared memory
    (the router has it on too), intact; a small message and a sender with it off go over the
    link; every segment left behind once the sessions close is removed."""
    senders = {"on": router.bus("camera"),
               "off": router.bus("camera", WAVEGRASP_SHARED_MEMORY_MB="0")}
    receiver = router.bus()
    try:
        receiver.subscribe("wavegrasp/test/cloud", lambda d: None)
        time.sleep(1.0)
        cloud = bytes(range(256)) * 8192  # 2 MB
        for name, payload in [("on", cloud), ("on", cloud), ("on", b"small"), ("off", cloud)]:
            senders[name].publish_cdr("wavegrasp/test/cloud", payload,
                                      "sensor_msgs/msg/PointCloud2")
            got = receiver.inbox.get(timeout=5)
            assert got.payload == payload and receiver.dispatch(got)
        assert receiver.received["wavegrasp/test/cloud"] == 4
        # The large ones sent on, the first too; none where this process may not lock memory
        # without limit.
        expected = 2 if memory_lock_limit() is None else 0
        assert receiver.received_shared["wavegrasp/test/cloud"] == expected
        assert not senders["on"].pool_full
    finally:
        for bus in [*senders.values(), receiver]:
            bus.close()
    remove_orphaned_segments()
    own = [p for p in Path("/dev/shm").glob("*.zenoh") if p.stem.isdigit()]
    with contextlib.ExitStack() as held:  # none of ours left; another user's live ones stay
        for path in own:
            with contextlib.suppress(OSError):
                fd = os.open(path, os.O_RDONLY)
                held.callback(os.close, fd)
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
                raise AssertionError(f"{path} is held by no process but was left")


@pytest.mark.skipif(memory_lock_limit() is not None, reason="shared memory needs unlimited "
                    "locked memory")
def test_a_full_pool_sends_over_the_link_and_counts_it(router: Router) -> None:
    """A receiver that holds the frames it got (one starved of CPU) fills the sender's pool:
    the next frames go over the link, counted, and every receiver still gets every frame."""
    sender = router.bus("camera", WAVEGRASP_SHARED_MEMORY_MB="3")
    receiver = router.bus()
    try:
        receiver.subscribe("wavegrasp/test/cloud", lambda d: None)
        holder = receiver.session.declare_subscriber("wavegrasp/test/cloud",
                                                     zenoh.handlers.FifoChannel(64))
        time.sleep(1.0)
        clouds = [bytes([k]) * 1_000_000 for k in range(6)]
        for cloud in clouds:
            sender.publish_cdr("wavegrasp/test/cloud", cloud, "sensor_msgs/msg/PointCloud2")
        for cloud in clouds:
            got = receiver.inbox.get(timeout=5)
            assert got.payload == cloud and receiver.dispatch(got)
        held = [holder.recv() for _ in clouds]  # kept: the pool stays full meanwhile
        assert [bytes(s.payload.to_bytes()) for s in held] == clouds
        shared = receiver.received_shared["wavegrasp/test/cloud"]
        assert 1 <= shared < len(clouds)
        assert sender.pool_full["wavegrasp/test/cloud"] == len(clouds) - shared
        holder.undeclare()
    finally:
        sender.close()
        receiver.close()
    remove_orphaned_segments()


@pytest.mark.skipif(memory_lock_limit() is not None, reason="shared memory needs unlimited "
                    "locked memory")
def test_a_pool_that_cannot_be_made_leaves_large_messages_to_the_link(router: Router) -> None:
    sender = router.bus("camera", WAVEGRASP_SHARED_MEMORY_MB=str(1 << 26))  # 64 TB
    receiver = router.bus()
    try:
        receiver.subscribe("wavegrasp/test/cloud", lambda d: None)
        time.sleep(1.0)
        cloud = bytes(range(256)) * 4096
        for _ in range(2):
            sender.publish_cdr("wavegrasp/test/cloud", cloud, "sensor_msgs/msg/PointCloud2")
            got = receiver.inbox.get(timeout=5)
            assert got.payload == cloud and receiver.dispatch(got)
        assert not receiver.received_shared and not sender.pool_full
    finally:
        sender.close()
        receiver.close()


def test_only_segments_no_process_holds_are_removed(tmp_path: Path) -> None:
    held, orphan, other = (tmp_path / n for n in ("11.zenoh", "12.zenoh", "notes.zenoh"))
    for path in (held, orphan, other):
        path.write_bytes(b"x")
    fd = os.open(held, os.O_RDONLY)
    try:
        fcntl.flock(fd, fcntl.LOCK_SH)  # as zenoh holds a segment it maps
        assert remove_orphaned_segments(tmp_path) == 1
    finally:
        os.close(fd)
    assert held.exists() and not orphan.exists() and other.exists()


@pytest.mark.parametrize("ipc_lock", [False, True])
def test_shared_memory_only_where_locked_memory_is_unlimited(ipc_lock: bool) -> None:
    """Zenoh locks its pools in memory: under a limit it stalls or refuses them, so the bus
    turns shared memory off there (a process without CAP_IPC_LOCK, as users and containers)."""
    if ipc_lock and os.geteuid() != 0:
        pytest.skip("only root holds CAP_IPC_LOCK here")
    code = "from wavegrasp.runtime.bus import memory_lock_limit; print(memory_lock_limit())"
    caps = [] if ipc_lock else ["setpriv", "--inh-caps=-all", "--bounding-set=-ipc_lock"]
    out = subprocess.run(["prlimit", "--memlock=4194304", *caps, sys.executable, "-c", code],
                         capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == ("None" if ipc_lock else "4194304")


def test_a_router_holds_its_hold_keys_off_the_hold_interfaces(tmp_path: Path) -> None:
    """The vehicle's router never sends the camera's full clouds out through the tether's
    interface, whoever subscribes to them there (zenoh's access control per interface);
    everything else passes. Here the held interface is the loopback, the subscriber's."""
    from wavegrasp.runtime.bus import Bus
    from wavegrasp.runtime.settings import Settings

    from conftest import free_port, wavegrasp_cmd

    port = free_port()
    endpoint = f"tcp/127.0.0.1:{port}"
    proc = spawn(wavegrasp_cmd("router", "--listen", endpoint),
                 {"WAVEGRASP_HOLD_KEYS": "trisect/points", "WAVEGRASP_HOLD_INTERFACES": "lo"})
    env = {"ZENOH_CONNECT": endpoint}
    camera = topside = None
    try:
        camera = Bus(Settings.from_env("player", env=env, connect_timeout_s=15))
        topside = Bus(Settings.from_env("recorder", env=env))
        got: list[str] = []
        topside.subscribe("**", lambda d: got.append(d.key))
        time.sleep(0.5)
        for _ in range(5):
            camera.publish_bytes("trisect/points", b"cloud")
            camera.publish_bytes("tf_static", b"frames")
        def drain() -> int:
            while not topside.inbox.empty():
                topside.dispatch(topside.inbox.get())
            return got.count("tf_static")

        assert wait_until(lambda: drain() == 5, timeout=10)
        time.sleep(0.3)  # the clouds, sent alongside, would have come by now
        drain()
        assert "trisect/points" not in got
    finally:
        for bus in (camera, topside):
            if bus is not None:
                bus.close()
        stop(proc)

"""A typed bus over Eclipse Zenoh: pydantic messages as CDR of their ROS 2 types
(``wavegrasp_msgs``, :mod:`wavegrasp.schemas.ros`), ROS messages as raw CDR.

Zenoh delivers samples on the thread that receives them from the link; the bus only copies
each one into the service's inbox there, and :meth:`Bus.dispatch` decodes and handles it on the
service's own loop. A payload that fails to decode, or whose handler raises, is counted and
logged under its key and never stops the service.
"""

from __future__ import annotations

import contextlib
import fcntl
import json
import logging
import os
import queue
import resource
import threading
import time
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import zenoh
from pydantic import BaseModel, ValidationError

from wavegrasp.runtime.settings import Settings
from wavegrasp.runtime.trace import CdrAttachment, publisher_gid, stamp_sent
from wavegrasp.schemas import MESSAGE_TYPES, health_key, instance_key
from wavegrasp.schemas.ros import from_cdr, to_cdr
from wavegrasp.schemas.ros import msgtype as ros_msgtype

log = logging.getLogger(__name__)

JSON = "application/json"
CDR = "application/cdr"
#: Zenoh's transmit queue for data holds 2 batches of 64 kB by default: a 440 kB camera cloud
#: then leaves in steps, each waiting for the link to drain the last, and the player's ``put``
#: took 1.1 ms instead of 0.4 ms (measured in ``wavegrasp up --pace realtime`` runs); 16
#: batches hold a whole cloud and more. A config file that sets the queue keeps its own.
DATA_QUEUE = "transport/link/tx/queue/size/data"
ZENOH_DATA_QUEUE = 2
DATA_QUEUE_BATCHES = 16
#: A router or peer waits this long in ``zenoh.open`` for scouting to find others (zenoh's
#: default, 500 ms, when the key is unset): with multicast scouting off there is nothing to
#: find, and every ``wavegrasp up`` waited half a second for its router (0.5 s -> 2 ms,
#: ``zenoh.open`` of a router on loopback). A config file that sets it keeps its own.
SCOUTING_DELAY = "scouting/delay"

#: Zenoh's shared memory between the processes of one host: a message of at least
#: SHARED_MEMORY_MIN_BYTES (camera clouds) is written once into the sender's pool and the
#: router and every receiver on this host read it there; a receiver that cannot map it
#: (another host, another container's /dev/shm) gets a copy over the link. The bus fills the
#: pool itself (:meth:`Bus.shared_payload`), not zenoh's transport: the transport copied
#: each message twice on the way in (3.3 + 1.7 ms for 8 MB), and with its pool full (a
#: receiver starved of CPU holding its frames) it held each put back about 200 ms; the
#: bus's puts go over the link at once instead and are counted. The few kB of predictions
#: and plans are copied (microseconds).
SHARED_MEMORY = "transport/shared_memory"
SHARED_MEMORY_MIN_BYTES = 64 * 1024

CAP_IPC_LOCK = 14


def memory_lock_limit() -> int | None:
    """This process's limit on locked memory, bytes, or None where it has none (unlimited,
    or root's CAP_IPC_LOCK). Zenoh locks its pools in memory, a sender's and every pool a
    receiver maps: under a limit (8 MB for most users, and in containers) a pool larger than
    it is never made, and one smaller stalled the messages it carried (measured: 1 of 10
    arrived in 20 s). So shared memory is used only where nothing limits it."""
    soft, _ = resource.getrlimit(resource.RLIMIT_MEMLOCK)
    if soft == resource.RLIM_INFINITY:
        return None
    with contextlib.suppress(OSError, ValueError, StopIteration):
        status = Path("/proc/self/status").read_text().splitlines()
        effective = int(next(line for line in status if line.startswith("CapEff:")).split()[1], 16)
        if effective >> CAP_IPC_LOCK & 1:
            return None
    return soft


@dataclass(frozen=True)
class Delivery:
    """One sample as it arrived: key, raw payload, encoding text, attachment, wall recv time."""

    key: str
    payload: bytes
    encoding: str
    attachment: bytes | None
    recv_ns: int
    route: int

    @property
    def schema(self) -> str | None:
        """The schema named in the encoding (``application/json;NAME``), if any."""
        _, sep, schema = self.encoding.partition(";")
        return schema or None if sep else None


class BadMessage(ValueError):
    """A payload that cannot be used; the text says what is wrong with it."""


def config_file(settings: Settings) -> str | None:
    """The zenoh config file ``settings.zenoh_config`` names for this service, if any."""
    if not settings.zenoh_config:
        return None
    return settings.zenoh_config.replace("{service}", settings.service)


def shared_memory_on(settings: Settings) -> bool:
    """Whether ``settings`` ask for shared memory and this process may lock memory without
    limit (see :func:`memory_lock_limit`)."""
    if settings.shared_memory_mb <= 0:
        return False
    limit = memory_lock_limit()
    if limit is not None:
        log.debug("%s: shared memory off: locked memory is limited to %d kB here (zenoh "
                  "locks its pools); unlimited, large messages would pass without a copy",
                  settings.service, limit >> 10)
    return limit is None


def zenoh_config(settings: Settings, shared_memory: bool | None = None) -> zenoh.Config:
    """Zenoh config: the file from ``ZENOH_CONFIG`` if any (credentials, access control, TLS),
    then our mode and explicit endpoints, multicast scouting off and shared memory on top
    (``shared_memory``; None: as :func:`shared_memory_on` says), and no wait for scouting in
    ``open`` unless the file asks for one.

    Raises
    ------
    ValueError
        naming the file, if it cannot be read or is not a zenoh config.
    """
    path = config_file(settings)
    try:
        conf = zenoh.Config.from_file(path) if path else zenoh.Config()
    except (zenoh.ZError, OSError) as exc:
        raise ValueError(f"{settings.service}: {path}: not a usable zenoh config: {exc}") from None
    conf.insert_json5("mode", json.dumps(settings.zenoh_mode))
    if settings.zenoh_mode != "router":
        conf.insert_json5("connect/endpoints", json.dumps(settings.zenoh_connect))
    elif settings.router_connect:  # a router's to another: keep trying while it is away
        conf.insert_json5("connect/endpoints", json.dumps(settings.router_connect))
        conf.insert_json5("connect/exit_on_failure", json.dumps({"router": False}))
    conf.insert_json5("listen/endpoints", json.dumps(settings.zenoh_listen))
    if settings.zenoh_mode == "router" and settings.hold_keys and settings.hold_interfaces:
        hold_back(conf, settings.hold_keys, settings.hold_interfaces)
    conf.insert_json5("scouting/multicast/enabled", "false")
    if shared_memory is None:
        shared_memory = shared_memory_on(settings)
    conf.insert_json5(SHARED_MEMORY + "/enabled", json.dumps(shared_memory))
    conf.insert_json5(SHARED_MEMORY + "/transport_optimization/enabled", "false")
    if json.loads(conf.get_json(DATA_QUEUE)) == ZENOH_DATA_QUEUE:  # unless the file set it
        conf.insert_json5(DATA_QUEUE, json.dumps(DATA_QUEUE_BATCHES))
    if json.loads(conf.get_json(SCOUTING_DELAY)) is None:
        conf.insert_json5(SCOUTING_DELAY, "0")
    return conf


def hold_back(conf: zenoh.Config, keys: list[str], interfaces: list[str]) -> None:
    """A router's ``conf`` never sends a publication on ``keys`` out through ``interfaces``
    (zenoh's access control, a deny rule per interface: a deny wins over any allow): added to
    the file's own rules if it has any, else alone with everything else allowed."""
    acl = json.loads(conf.get_json("access_control"))
    if not acl.get("enabled"):
        acl = {"enabled": True, "default_permission": "allow", "rules": [], "subjects": [],
               "policies": []}
    acl["rules"] = [*acl.get("rules", []), {
        "id": "hold back", "permission": "deny", "flows": ["egress"],
        "messages": ["put", "delete"], "key_exprs": keys}]
    acl["subjects"] = [*acl.get("subjects", []), {"id": "held", "interfaces": interfaces}]
    acl["policies"] = [*acl.get("policies", []), {
        "id": "hold back", "rules": ["hold back"], "subjects": ["held"]}]
    conf.insert_json5("access_control", json.dumps(acl))


def open_session(settings: Settings, shared_memory: bool | None = None) -> zenoh.Session:
    """Open a session, retrying until ``connect_timeout_s`` while the router comes up;
    ``shared_memory``: as :func:`zenoh_config`'s (None: as the settings and this process's
    locked-memory limit allow)."""
    deadline = time.monotonic() + settings.connect_timeout_s
    while True:
        try:
            return zenoh.open(zenoh_config(settings, shared_memory))
        except zenoh.ZError as exc:
            if settings.zenoh_mode == "router" or time.monotonic() > deadline:
                where = settings.zenoh_listen if settings.zenoh_mode == "router" else (
                    settings.zenoh_connect)
                path = config_file(settings)
                using = f" with {path}" if path else ""
                raise ConnectionError(f"{settings.service}: cannot open zenoh session on "
                                      f"{', '.join(where)}{using}: {exc}") from None
            time.sleep(0.05)  # a router started a moment ago listens within milliseconds


class Bus:
    """A service's zenoh session: typed publish/subscribe, liveliness, per-key counters."""

    def __init__(self, settings: Settings, session: zenoh.Session | None = None) -> None:
        self.service = settings.service
        self.mode = settings.zenoh_mode
        shared_memory = shared_memory_on(settings)  # once: it reads /proc and may log
        self.session = session if session is not None else open_session(settings,
                                                                         shared_memory)
        self.inbox: queue.SimpleQueue[Delivery] = queue.SimpleQueue()
        self.received: Counter[str] = Counter()
        self.received_shared: Counter[str] = Counter()  # of them, through shared memory
        #: Large messages sent over the link because the pool was full, per key.
        self.pool_full: Counter[str] = Counter()
        self._pool_bytes = settings.shared_memory_mb << 20 if shared_memory else 0
        self._pool: zenoh.shm.ShmProvider | None = None
        self.bad: Counter[str] = Counter()
        self.last_bad_reason: dict[str, str] = {}
        self.subscriptions: list[str] = []
        self._routes: list[Callable[[Delivery], None]] = []
        self._publishers: dict[str, zenoh.Publisher] = {}
        self.urgent: set[str] = set()  # keys sent ahead of the rest (mark_urgent)
        self._seq: Counter[str] = Counter()
        self._keep: list[Any] = []  # subscribers and tokens live as long as the bus
        self._lock = threading.Lock()
        self.alive: set[str] = set()  # kept up to date once watch_alive() is called
        self.alive_since: dict[str, float] = {}  # monotonic time a process of each last appeared
        self.gone_since: dict[str, float] = {}  # monotonic time a process of each last went

    # -- publishing ---------------------------------------------------------------------------
    def mark_urgent(self, *keys: str) -> None:
        """Send ``keys`` ahead of everything else on every link (zenoh's interactive-high
        priority, unbatched): the gate's decisions and the arm's commands and state must not
        wait behind camera clouds on a busy tether. Only ever raised: a service's frame
        acknowledgement, sent after its data at the normal priority, still never overtakes it."""
        self.urgent.update(keys)

    def _publisher(self, key: str, encoding: zenoh.Encoding) -> zenoh.Publisher:
        pub = self._publishers.get(key)
        if pub is None:
            urgent = key in self.urgent
            pub = self.session.declare_publisher(
                key, encoding=encoding, congestion_control=zenoh.CongestionControl.BLOCK,
                priority=zenoh.Priority.INTERACTIVE_HIGH if urgent else zenoh.Priority.DATA,
                express=urgent)
            self._publishers[key] = pub
        return pub

    def publish(self, key: str, msg: BaseModel) -> None:
        """Publish ``msg`` on ``key`` as CDR of its ``wavegrasp_msgs`` type (encoding
        ``application/cdr;wavegrasp_msgs/msg/NAME``), stamping this service's hop as sent.
        A model that is not one of our messages (a tool's own) goes as JSON
        (``application/json;NAME``)."""
        header = getattr(msg, "header", None)
        if header is not None:
            stamp_sent(header, self.service)
        name = type(msg).__name__
        if MESSAGE_TYPES.get(name) is type(msg):
            self._publisher(key, zenoh.Encoding(f"{CDR};{ros_msgtype(name)}")).put(to_cdr(msg))
        else:
            self._publisher(key, zenoh.Encoding(f"{JSON};{name}")).put(
                msg.model_dump_json().encode())

    def publish_cdr(self, key: str, cdr: bytes, msgtype: str, log_time_ns: int = 0,
                    source: CdrAttachment | None = None) -> int:
        """Publish CDR bytes unchanged on ``key`` with an attachment; returns its sequence.
        ``source``: the attachment of the message this one stands for (a camera frame the
        edge reduced), whose sequence, publish time and log time it keeps, so frames are
        acknowledged and timed from the camera as before."""
        with self._lock:
            seq = self._seq[key] if source is None else source.seq
            self._seq[key] += 1
        gid = publisher_gid(self.service, key)
        att = (CdrAttachment(seq, time.time_ns(), gid, log_time_ns) if source is None else
               CdrAttachment(seq, source.source_ns, gid, source.log_time_ns))
        self._publisher(key, zenoh.Encoding(f"{CDR};{msgtype}")).put(
            self.shared_payload(key, cdr), attachment=att.encode())
        return seq

    def shared_payload(self, key: str, data: bytes) -> bytes | zenoh.shm.ZShmMut:
        """``data`` written into this process's shared-memory pool if it is large and the
        pool has room (made on first use), else ``data`` itself (counted in
        :attr:`pool_full` when the pool had no room: never waited for)."""
        if not self._pool_bytes or len(data) < SHARED_MEMORY_MIN_BYTES:
            return bytes(data)
        if self._pool is None:
            try:
                self._pool = zenoh.shm.ShmProvider.default_backend(self._pool_bytes)
            except zenoh.ZError as exc:  # /dev/shm too small, a size zenoh refuses...
                log.warning("%s: no %d MB shared-memory pool (%s): large messages go over "
                            "the link", self.service, self._pool_bytes >> 20, exc)
                self._pool_bytes = 0
                return bytes(data)
        try:
            buf = self._pool.alloc(len(data), policy=zenoh.shm.GarbageCollect())
        except zenoh.ZError:
            self.pool_full[key] += 1
            return bytes(data)
        buf[:] = data
        return buf

    def published(self) -> dict[str, int]:
        """CDR messages published so far, per key."""
        with self._lock:
            return dict(self._seq)

    def continue_sequences(self, published: dict[str, int]) -> None:
        """Go on from ``published`` CDR messages per key (a restarted source resuming), so
        sequence numbers and :meth:`published` counts carry on where they were."""
        with self._lock:
            self._seq.update({key: int(n) for key, n in published.items()})

    def publish_bytes(self, key: str, payload: bytes, encoding: str = JSON) -> None:
        """Publish raw bytes (tools and fault injection); services use the typed calls."""
        self.session.put(key, payload, encoding=zenoh.Encoding(encoding),
                         congestion_control=zenoh.CongestionControl.BLOCK)

    # -- subscribing --------------------------------------------------------------------------
    def subscribe(self, key: str, handler: Callable[..., None],
                  model: type[BaseModel] | None = None) -> None:
        """Call ``handler`` on the service loop for every sample on ``key``.

        With ``model``, the handler gets ``(msg, delivery)`` with the decoded model; without,
        it gets ``(delivery)`` and raises :class:`BadMessage` (or ValueError) on bad input.

        Each key has its own zenoh subscriber, so the router sends this service only what it
        asked for. Their callbacks run on the thread that receives the link's samples, one
        after the other in the order they arrived, so one publisher's messages reach the
        inbox in the order they were sent, whatever their keys: a frame acknowledgement never
        overtakes the data it acknowledges. (zenoh-python's default would run each
        subscriber's callbacks on a Python thread of its own: concurrently, and one more
        thread wake-up per message.) The price: while the service loop runs Python, a sample
        waits for the interpreter lock there, at most the loop's switch interval
        (``Settings.switch_interval_ms``), and the session's later samples wait behind it.
        """
        if model is None:
            route = handler
        else:
            def route(d: Delivery) -> None:
                handler(decode_model(d, model), d)
        with self._lock:
            index = len(self._routes)
            self._routes.append(route)
        self.subscriptions.append(key)
        self._keep.append(self.session.declare_subscriber(key, zenoh.handlers.Callback(
            lambda sample: self._deliver(sample, index), indirect=False)))

    def _deliver(self, sample: zenoh.Sample, route: int) -> None:
        att = sample.attachment
        if sample.payload.as_shm() is not None:
            self.received_shared[str(sample.key_expr)] += 1
        self.inbox.put(Delivery(
            key=str(sample.key_expr), payload=sample.payload.to_bytes(),
            encoding=str(sample.encoding), attachment=None if att is None else att.to_bytes(),
            recv_ns=time.time_ns(), route=route))

    def dispatch(self, delivery: Delivery) -> bool:
        """Decode and handle one delivery; count it; False if it was bad."""
        self.received[delivery.key] += 1
        try:
            self._routes[delivery.route](delivery)
            return True
        except (BadMessage, ValueError, ValidationError) as exc:
            self.count_bad(delivery.key, str(exc).splitlines()[0][:300])
        except Exception as exc:  # a handler bug must not kill the service either
            log.exception("%s: handler failed on %s", self.service, delivery.key)
            self.count_bad(delivery.key, f"{type(exc).__name__}: {exc}"[:300])
        return False

    def count_bad(self, key: str, reason: str) -> None:
        self.bad[key] += 1
        self.last_bad_reason[key] = reason
        log.warning("%s: bad message on %s (%d so far): %s", self.service, key, self.bad[key],
                    reason)

    # -- health -------------------------------------------------------------------------------
    def declare_alive(self) -> None:
        """Hold the liveliness tokens ``wavegrasp/health/<service>`` and
        ``wavegrasp/health/<service>/<session id>`` until the bus closes."""
        liveliness = self.session.liveliness()
        self._keep.append(liveliness.declare_token(health_key(self.service)))
        self._keep.append(liveliness.declare_token(
            instance_key(self.service, str(self.session.info.zid()))))

    def reaches_network(self) -> bool:
        """Whether the session is connected: a client or peer to a router, a router always."""
        return self.mode == "router" or bool(self.session.info.routers_zid())

    def alive_services(self, timeout_s: float = 1.0) -> set[str]:
        """Names of services whose liveliness token is visible now."""
        replies = self.session.liveliness().get(health_key("*"), timeout=timeout_s)
        names = set()
        for reply in replies:
            if reply.ok is not None:
                names.add(str(reply.ok.key_expr).rsplit("/", 1)[-1])
        return names

    def watch_alive(self) -> None:
        """Keep :attr:`alive` up to date from liveliness events (tokens that exist now, then
        each that appears or goes), rather than asking the router each time."""
        def on_token(sample: zenoh.Sample) -> None:
            name = str(sample.key_expr).rsplit("/", 1)[-1]
            with self._lock:  # zenoh's thread; readers take a copy under the lock
                if sample.kind == zenoh.SampleKind.DELETE:
                    self.alive.discard(name)
                else:
                    self.alive.add(name)

        def on_instance(sample: zenoh.Sample) -> None:
            # The service's own token shows no new process while a dead one's lingers.
            name = str(sample.key_expr).rsplit("/", 2)[-2]
            since = self.alive_since if sample.kind == zenoh.SampleKind.PUT else self.gone_since
            with self._lock:
                since[name] = time.monotonic()

        liveliness = self.session.liveliness()
        self._keep.append(liveliness.declare_subscriber(health_key("*"), on_token, history=True))
        self._keep.append(liveliness.declare_subscriber(
            instance_key("*", "*"), on_instance, history=True))

    def alive_now(self) -> set[str]:
        """A copy of the services alive, as :meth:`watch_alive` sees them."""
        with self._lock:
            return set(self.alive)

    def wait_for_services(self, names: list[str], timeout_s: float) -> set[str]:
        """Wait until every service in ``names`` is alive; returns those still missing."""
        deadline = time.monotonic() + timeout_s
        missing = set(names)
        while missing and time.monotonic() < deadline:
            missing -= self.alive_services(timeout_s=min(1.0, timeout_s))
            if missing:
                time.sleep(0.05)
        return missing

    def close(self) -> None:
        for item in [*reversed(self._keep), *self._publishers.values()]:
            with contextlib.suppress(zenoh.ZError):
                item.undeclare()
        self._keep.clear()
        self._publishers.clear()
        self.session.close()


def remove_orphaned_segments(directory: Path = Path("/dev/shm")) -> int:
    """Remove the shared-memory segments of zenoh (``<number>.zenoh`` in ``directory``) that
    no process holds any more; returns how many. Each session leaves its own behind when it
    ends, and zenoh removes them only when the next session with shared memory opens (the
    same test, which zenoh-python does not expose): every process that maps a segment holds
    a shared lock on it, so an exclusive one is granted only on a segment nobody uses."""
    removed = 0
    for path in directory.glob("*.zenoh"):
        if not path.stem.isdigit():
            continue
        try:
            fd = os.open(path, os.O_RDONLY)
        except OSError:  # gone meanwhile, or another user's
            continue
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            path.unlink(missing_ok=True)
            removed += 1
        except OSError:  # in use
            pass
        finally:
            os.close(fd)
    return removed


def cdr_meta(d: Delivery, types: dict[str, str]) -> tuple[str, CdrAttachment | None]:
    """A CDR delivery's message type (from its encoding, else ``types`` by key) and its
    attachment; BadMessage naming the key when either is missing or malformed."""
    msgtype = d.schema or types.get(d.key)
    if msgtype is None:
        raise BadMessage(f"{d.key}: CDR payload without a message type in its encoding")
    try:
        return msgtype, CdrAttachment.decode(d.attachment)
    except ValueError as exc:
        raise BadMessage(f"{d.key}: {exc}") from None


def decode_model(delivery: Delivery, model: type[BaseModel]) -> BaseModel:
    """Decode a payload as ``model``: CDR of its ``wavegrasp_msgs`` type, or JSON of the model
    (what a tool or an older sender may publish); raises :class:`BadMessage` naming key and
    problem."""
    kind = delivery.encoding.split(";")[0]
    expected = ros_msgtype(model.__name__) if kind == CDR else model.__name__
    if kind not in (CDR, JSON, "text/json", "zenoh/bytes"):
        raise BadMessage(f"{delivery.key}: encoding {delivery.encoding!r}, expected {CDR} or "
                         f"{JSON}")
    if delivery.schema is not None and delivery.schema != expected:
        raise BadMessage(f"{delivery.key}: encoding names schema {delivery.schema}, expected "
                         f"{expected}")
    try:
        if kind == CDR:
            return from_cdr(delivery.payload, model)
        return model.model_validate_json(delivery.payload)
    except ValidationError as exc:
        err = exc.errors()[0]
        where = ".".join(str(p) for p in err["loc"]) or "payload"
        raise BadMessage(f"{delivery.key}: {model.__name__}.{where}: {err['msg']}") from None
    except ValueError as exc:  # not CDR of the type at all
        raise BadMessage(f"{delivery.key}: {exc}") from None

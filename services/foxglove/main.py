"""``wavegrasp foxglove``: the bus, live, for Foxglove (the app or app.foxglove.dev).

Subscribes to ``serve_keys`` (everything by default) and serves each CDR key as a Foxglove channel
(topic ``/`` + key, ``cdr`` messages, the type's ``ros2msg`` schema, as run.mcap has it)
over the Foxglove WebSocket protocol (foxglove-sdk) on ``foxglove_host``:``foxglove_port``
(127.0.0.1:8765: open ``ws://localhost:8765`` in Foxglove). Every key of the contract that
``serve_keys`` covers has its channel from the start (``known_channels``); any other key's
appears with its first message. The camera's clouds, the perception's points, the scene's
markers and ``/tf``, the arm's ``joint_states`` and every message of ours are drawn or
plotted by Foxglove's panels (``ops/foxglove/layout.json``). Messages go out with their log
time (the recording's clock), so Foxglove's timeline follows the replay.
"""

from __future__ import annotations

import logging
import sys

import foxglove
import zenoh
from pydantic import Field

from wavegrasp.recording_io.typestore import ros2_msgdef
from wavegrasp.runtime.bus import CDR, BadMessage, Bus, Delivery, cdr_meta, ros_msgtype
from wavegrasp.runtime.service import Service, service_main
from wavegrasp.runtime.settings import Settings
from wavegrasp.schemas import KEY_TYPES, ROS_KEYS, SCENE_KEYS

log = logging.getLogger("wavegrasp.foxglove")


class FoxgloveSettings(Settings):
    foxglove_host: str = Field("127.0.0.1", description="where the WebSocket server listens "
                               "(0.0.0.0: every interface; keep it on the loopback unless the "
                               "link is trusted: the protocol has no login)")
    foxglove_port: int = Field(8765, ge=0, le=65535, description="its port (0: any free one)")
    serve_keys: list[str] = Field(default_factory=lambda: ["**"], description="key expressions "
                            "to serve")


class FoxgloveBridge(Service):
    subscribes_clock = False  # its own subscription brings the ticks

    def __init__(self, settings: FoxgloveSettings, bus: Bus | None = None) -> None:
        super().__init__(settings, bus)
        self.server = foxglove.start_server(name="wavegrasp", host=settings.foxglove_host,
                                            port=settings.foxglove_port)
        self.channels: dict[str, foxglove.Channel] = {}
        for key, msgtype in known_channels(settings.serve_keys).items():
            self.channel(key, msgtype)
        for expr in settings.serve_keys:
            self.bus.subscribe(expr, self.on_message)
        log.info("serving the bus for Foxglove on ws://%s:%d", settings.foxglove_host,
                 self.server.port)

    def channel(self, key: str, msgtype: str) -> foxglove.Channel:
        """The key's channel in ``msgtype``'s schema, made if new; BadMessage if the key's
        channel has another type."""
        channel = self.channels.get(key)
        if channel is not None and channel.schema_name() != msgtype:
            raise BadMessage(f"{key}: a {msgtype} message on a channel of "
                             f"{channel.schema_name()}")
        if channel is None:
            try:
                definition = ros2_msgdef(msgtype)
            except Exception as exc:  # rosbags raises several types for an unknown type
                raise BadMessage(f"{key}: no ROS 2 definition of {msgtype!r}: {exc}") from None
            channel = foxglove.Channel(f"/{key}", message_encoding="cdr", schema=foxglove.Schema(
                name=msgtype, encoding="ros2msg", data=definition.encode()))
            self.channels[key] = channel
            self.counters["channels"] = len(self.channels)
        return channel

    def on_message(self, d: Delivery) -> None:
        if not d.encoding.startswith(CDR):
            self.counters["not CDR: not served"] += 1
            return
        msgtype, att = cdr_meta(d, ROS_KEYS)
        log_time = att.log_time_ns if att is not None and att.log_time_ns else (
            self.clock.now_ns() or None)
        self.channel(d.key, msgtype).log(d.payload, log_time=log_time)
        self.counters["served"] += 1

    def on_stop(self) -> None:
        self.server.stop()


def known_channels(serve_keys: list[str]) -> dict[str, str]:
    """The contract's keys (ours, the ROS ones, the scene's) that ``serve_keys`` covers, each
    with its ROS 2 type.

    Made before any client connects because foxglove-sdk (0.30) loses a channel made while a
    client is connected when the client subscribes quickly: the server sends the
    advertisement before it adds the channel to the client's table, and refuses the
    subscription that comes in between; and the message a channel is made with never reaches
    a client already connected, so single messages (a plan, an outcome) were missed live.
    """
    exprs = [zenoh.KeyExpr(e) for e in serve_keys]
    typed = {**{k: ros_msgtype(m.__name__) for k, m in KEY_TYPES.items()}, **ROS_KEYS,
             **SCENE_KEYS}
    return {k: t for k, t in typed.items() if any(e.intersects(zenoh.KeyExpr(k)) for e in exprs)}


def main(argv: list[str] | None = None) -> int:
    try:
        return service_main("foxglove", __doc__, FoxgloveSettings, FoxgloveBridge, argv)
    except RuntimeError as exc:  # foxglove-sdk's, e.g. the port taken
        print(f"wavegrasp foxglove: cannot serve: {exc}", file=sys.stderr)
        return 2

"""A minimal service for the bus tests: echoes ``test/ping`` observations to ``test/pong``.

It is a real separate process built on the shared runtime, so the tests exercise the typed
bus, the trace header and the service loop exactly as a wavegrasp service uses them.
"""

from __future__ import annotations

import sys

from wavegrasp.runtime.bus import Delivery
from wavegrasp.runtime.service import Service, setup_logging
from wavegrasp.runtime.settings import Settings
from wavegrasp.runtime.trace import derived_header
from wavegrasp.schemas import ObjectObservation


class Echo(Service):
    def __init__(self, settings: Settings) -> None:
        super().__init__(settings)
        self.bus.subscribe("test/ping", self.on_ping, ObjectObservation)

    def on_ping(self, msg: ObjectObservation, d: Delivery) -> None:
        out = msg.model_copy(update={"header": derived_header(msg.header, self.name, d.recv_ns)})
        self.bus.publish("test/pong", out)


if __name__ == "__main__":
    setup_logging()
    sys.exit(Echo(Settings.from_env(sys.argv[1] if len(sys.argv) > 1 else "echo")).run())

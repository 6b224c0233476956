"""A file whose age says a process is up: what compose's healthcheck reads.

A check that opened a zenoh session of its own cost about 0.3 s of CPU; seven services
checked every 2 s took a core of a 2-core machine. Touching a file once a second costs
nothing, and ``find FILE -newermt '-3 seconds'`` in the container reads it.
"""

from __future__ import annotations

import contextlib
import time
from pathlib import Path

from wavegrasp.runtime.bus import Bus


class Heartbeat:
    """Touch ``path`` at most every ``period_s`` while ``bus`` reaches the zenoh network (a
    client: a router is connected; a router: its session is open). ``path`` None: no file.
    """

    def __init__(self, path: Path | None, period_s: float = 1.0) -> None:
        self.path = path
        self.period_s = period_s
        self._next = 0.0

    def beat(self, bus: Bus) -> None:
        now = time.monotonic()
        if self.path is None or now < self._next:
            return
        self._next = now + self.period_s
        if bus.reaches_network():
            with contextlib.suppress(OSError):  # a full or read-only /tmp: no file, unhealthy
                self.path.touch()

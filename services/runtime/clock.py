"""The time a service lives by: the recording's (``wavegrasp/clock``) or the wall's."""

from __future__ import annotations

import time

from wavegrasp.schemas import Clock


class RecordingClock:
    """Follows ``wavegrasp/clock``; until the first tick, and with ``wall=True``, wall time.

    Between ticks it advances with wall time scaled by the clock's rate (0 = frozen), so a
    service asking for ``now_ns()`` between two frames gets a sensible recording time.
    """

    def __init__(self, wall: bool = False) -> None:
        self.wall = wall
        self._stamp_ns: int | None = None
        self._at_mono_ns = 0
        self._rate = 1.0
        #: The player's CDR messages published so far, per key (as of the latest tick).
        self.published: dict[str, int] = {}

    def on_clock(self, msg: Clock) -> None:
        self._stamp_ns = msg.header.stamp_ns
        self._at_mono_ns = time.monotonic_ns()
        self._rate = msg.rate
        self.published = msg.published

    @property
    def rate(self) -> float:
        """Recording seconds per wall second: 1 live or realtime, 0 when the recording waits
        (lockstep, fast)."""
        return 1.0 if self.wall or self._stamp_ns is None else self._rate

    @property
    def started(self) -> bool:
        return self.wall or self._stamp_ns is not None

    def now_ns(self) -> int:
        """Recording time in ns (wall time before the first tick or in wall mode)."""
        if self.wall or self._stamp_ns is None:
            return time.time_ns()
        return self._stamp_ns + int((time.monotonic_ns() - self._at_mono_ns) * self._rate)

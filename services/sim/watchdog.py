"""The arm's watchdog: with no heartbeat from the gate for ``timeout_s``, the arm stops.

On a vehicle the gate is topside, across a tether that can drop; an arm that went on
following its last trajectory would move on commands nobody can revise or abort. So the
arm's side (the sim, or a real arm's driver) watches the gate's heartbeats
(``wavegrasp/gate/heartbeat``): armed by the first, it trips once ``timeout_s`` of wall time
pass without one, and the arm holds where it is commanded to be (an attempt under way ends
there, aborted: its plan's updates assumed an arm that went on); while tripped, new paths are
refused; the next heartbeat re-arms it. Times are monotonic seconds.
"""

from __future__ import annotations


class Watchdog:
    def __init__(self, timeout_s: float) -> None:
        if not timeout_s > 0:
            raise ValueError(f"watchdog timeout_s must be > 0, got {timeout_s}")
        self.timeout_s = timeout_s
        self.last: float | None = None  # the last heartbeat; None: not armed yet
        self.tripped = False

    def beat(self, now: float) -> bool:
        """A heartbeat at ``now``; returns whether it ends a trip (the link is back)."""
        back, self.tripped, self.last = self.tripped, False, now
        return back

    def silent(self, now: float) -> bool:
        """Whether armed, not tripped, and no heartbeat for longer than ``timeout_s``."""
        return not self.tripped and self.last is not None and now - self.last > self.timeout_s

    def check(self, now: float) -> bool:
        """Whether it trips at ``now`` (True once per silence)."""
        if not self.silent(now):
            return False
        self.tripped = True
        return True

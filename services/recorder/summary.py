"""What a run's ``summary.json`` says of the bus: each service's latest stats, the player's
status and every grasp outcome.

The recorder writes it when it stops (under ``docker compose``, nothing else sees the whole
run); ``wavegrasp up`` keeps one too and writes it over the recorder's, adding what only the
launcher knows (exit codes, restarts, duration).
"""

from __future__ import annotations

from collections import Counter, defaultdict

from wavegrasp.schemas import GraspOutcome, PlayerStatus, ServiceStats


class RunSummary:
    """Collects the messages a summary is made of; feed it with the ``on_*`` methods."""

    def __init__(self) -> None:
        self.stats: dict[str, dict] = {}
        self.outcomes: list[dict] = []
        self.player_status: dict = {}
        self._bad_before: dict[str, Counter[str]] = defaultdict(Counter)  # earlier processes
        self._bad_now: dict[str, Counter[str]] = {}
        self._uptime: dict[str, float] = {}

    def on_outcome(self, msg: GraspOutcome) -> None:
        self.outcomes.append(msg.model_dump(exclude={"header"}))

    def on_stats(self, msg: ServiceStats) -> None:
        """Keep each service's latest stats; bad-message counts add up across its restarts."""
        name = msg.service
        if msg.uptime_s < self._uptime.get(name, 0.0):  # a new process
            self._bad_before[name].update(self._bad_now[name])
        self._uptime[name], self._bad_now[name] = msg.uptime_s, Counter(msg.bad)
        stats = msg.model_dump(exclude={"header"})
        stats["bad"] = dict(self._bad_before[name] + self._bad_now[name])
        self.stats[name] = stats

    def on_status(self, msg: PlayerStatus) -> None:
        self.player_status = msg.model_dump(exclude={"header", "metadata"})

    def as_dict(self) -> dict:
        """The summary's fields that come from the bus."""
        return {
            "player": self.player_status,
            "bad_messages": {n: s["bad"] for n, s in self.stats.items() if s.get("bad")},
            "services": self.stats,
            "outcomes": self.outcomes,
        }

    def bad_total(self) -> int:
        return sum(sum(s["bad"].values()) for s in self.stats.values())

    def outcome_kinds(self) -> dict[str, int]:
        """Attempts by result: ``success``, ``aborted`` or the failure's kind."""
        return dict(Counter("success" if o["success"] else "aborted" if o.get("aborted")
                            else o["failure"] for o in self.outcomes))

"""A service's few facts on disk, so that a process restarted after a crash goes on from
where the last one was (compose restarts the same container, whose files are still there).
"""

from __future__ import annotations

import contextlib
import json
import logging
import os
from pathlib import Path

log = logging.getLogger(__name__)


class StateFile:
    """A small JSON file written whole each time (a kill never leaves half of one)."""

    def __init__(self, path: Path | None) -> None:
        self.path = path

    def load(self) -> dict | None:
        """The state saved last, or None if there is none (or no file is set). An unreadable
        file is named in a warning and ignored: the service starts afresh."""
        if self.path is None or not self.path.exists():
            return None
        try:
            state = json.loads(self.path.read_text())
        except (OSError, ValueError) as exc:
            log.warning("%s: unreadable state (%s); starting afresh", self.path, exc)
            return None
        if not isinstance(state, dict):
            log.warning("%s: state is not a JSON object; starting afresh", self.path)
            return None
        return state

    def save(self, state: dict) -> None:
        if self.path is None:
            return
        tmp = self.path.with_name(self.path.name + ".tmp")
        tmp.write_text(json.dumps(state))
        os.replace(tmp, self.path)

    def clear(self) -> None:
        """Forget the state (a finished job is not resumed)."""
        if self.path is not None:
            with contextlib.suppress(OSError):
                self.path.unlink()

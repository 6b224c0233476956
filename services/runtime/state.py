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


#: A state this long or shorter is written over the last in one page-sized write.
PAGE = 4096


class StateFile:
    """A small JSON file written whole each time (a kill never leaves half of one).

    The first save, and any longer than a page, goes to a new file renamed over the old;
    the next ones overwrite that file's one page in place, padded with spaces (JSON allows
    them): one write of one page is all or nothing for a killed process, and a rename on
    every camera frame cost the player 1 ms a frame (ext4), on the frame's path in lockstep.
    """

    def __init__(self, path: Path | None) -> None:
        self.path = path
        self._fd: int | None = None  # the file renamed into place last, open for writing

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
        data = json.dumps(state).encode()
        if self._fd is not None and len(data) <= PAGE:
            os.pwrite(self._fd, data.ljust(PAGE), 0)
            return
        self._close()
        tmp = self.path.with_name(self.path.name + ".tmp")
        tmp.write_bytes(data.ljust(PAGE))
        os.replace(tmp, self.path)
        if len(data) <= PAGE:
            self._fd = os.open(self.path, os.O_WRONLY)

    def clear(self) -> None:
        """Forget the state (a finished job is not resumed)."""
        self._close()
        if self.path is not None:
            with contextlib.suppress(OSError):
                self.path.unlink()

    def _close(self) -> None:
        if self._fd is not None:
            os.close(self._fd)
            self._fd = None

"""Service processes forked from one that has loaded their libraries already.

Each ``wavegrasp NAME`` service imports numpy, scipy, pydantic, zenoh and its own libraries
(open3d, pybullet, ruckig) before its first message: 0.2-1.0 CPU seconds apiece, 3.5 s for
a run's eight, against 1.1 s for all of them once (``/usr/bin/time python -c "import
wavegrasp.perception.main, ..."``). ``wavegrasp up`` starts them from multiprocessing's
fork server with those modules preloaded: each service is a fork of it that sets its own
environment, session and streams, then runs ``wavegrasp NAME`` as the command line would
(the same ``main``, placement and signal handling). Anything else the compose file runs is
started as a command, as is a service whose thread limits differ from the server's (the
numeric libraries read them once, when they load).
"""

from __future__ import annotations

import multiprocessing
import os
import subprocess
import sys
from multiprocessing.connection import Connection
from typing import IO

from setproctitle import setproctitle

from wavegrasp import cli
from wavegrasp.cli import SERVICES, THREAD_LIMITS

#: What the fork server imports once: every service's main module, then what freezes them.
PRELOAD = [f"wavegrasp.{name}.main" for name in (*sorted(SERVICES), "router")]
PRELOAD.append("wavegrasp.ops.preloaded")


def forkable(command: list[str], env: dict[str, str]) -> list[str] | None:
    """The ``wavegrasp`` arguments of ``command`` (a local command line) if it runs a service
    the fork server can start with ``env``; else None."""
    if command[:3] != [sys.executable, "-m", "wavegrasp"] or len(command) < 4:
        return None
    if command[3] not in SERVICES and command[3] != "router":
        return None
    if any(env.get(var) != os.environ.get(var) for var in THREAD_LIMITS):
        return None
    return command[3:]


def prepare() -> None:
    """Set the thread limits (as ``wavegrasp NAME`` does) in this process's environment, which
    the fork server inherits when it starts: call before the first :class:`ForkedService`."""
    for var in THREAD_LIMITS:
        os.environ.setdefault(var, "1")


class ForkedService:
    """A service forked by the fork server, with what the launcher uses of a Popen: ``pid``,
    ``stdout`` (bytes, its output and errors), ``poll``, ``wait``, ``returncode``."""

    def __init__(self, args: list[str], env: dict[str, str]) -> None:
        self.args = args
        read, write = os.pipe()
        out = Connection(write, readable=False)  # sent to the fork, closed here after
        context = multiprocessing.get_context("forkserver")
        context.set_forkserver_preload(PRELOAD)
        self._process = context.Process(target=_serve, args=(args, env, os.getcwd(), out),
                                        name=f"wavegrasp {args[0]}")
        try:
            self._process.start()
        finally:
            out.close()
        self.stdout: IO[bytes] = os.fdopen(read, "rb")
        assert self._process.pid is not None
        self.pid: int = self._process.pid

    @property
    def returncode(self) -> int | None:
        return self._process.exitcode

    def poll(self) -> int | None:
        return self._process.exitcode

    def wait(self, timeout: float | None = None) -> int:
        self._process.join(timeout)
        code = self._process.exitcode
        if code is None:
            raise subprocess.TimeoutExpired(["wavegrasp", *self.args], timeout or 0.0)
        return code


def _serve(args: list[str], env: dict[str, str], cwd: str, out: Connection) -> None:
    """In the fork: a session and process group of its own (the launcher signals the group),
    its output to ``out``, its environment, then ``wavegrasp ARGS``."""
    os.setsid()
    setproctitle(" ".join(["wavegrasp", *args]))  # what ps and top show, not the server's
    for fd in (1, 2):
        os.dup2(out.fileno(), fd)
    out.close()
    for stream in (sys.stdout, sys.stderr):
        stream.reconfigure(line_buffering=True, write_through=True)  # type: ignore[union-attr]
    os.environ.clear()
    os.environ.update(env)
    os.chdir(cwd)
    code = cli.main(args)
    sys.stdout.flush()
    sys.stderr.flush()
    sys.exit(code)

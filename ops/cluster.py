"""``wavegrasp eval --cluster ray://HOST:PORT``: the experiment's runs as Ray tasks.

Each run (one lockstep ``wavegrasp up``, about 1.2 cores busy) is a task asking for one CPU,
so Ray starts it on whichever node has one free. The task finds its recording in that node's
cache or generates it there (deterministic: every node makes the same file), runs it, writes
the run's folder under ``--out`` on that node and returns the run's figures, from which this
process writes the same report as a local experiment. With ``--out`` on storage the nodes
share (or a cluster of one machine) the run folders end up where a local run puts them.

Every node needs the same wavegrasp with the ``cluster`` extra (``pip install
'wavegrasp[cluster]'``: Ray with its client) and a cluster started without usage reporting::

    ray start --head --port 6379 --ray-client-server-port 10001 --disable-usage-stats
    ray start --address HEAD:6379 --disable-usage-stats        # on each other node
    wavegrasp eval --cluster ray://HEAD:10001 --out DIR ...

Ctrl-C cancels the runs under way (each stops its services) and starts no other.
"""

from __future__ import annotations

import os
import sys
import time
import warnings
from collections.abc import Callable, Sequence
from typing import Any

from tqdm import tqdm

#: How long the runs cancelled by Ctrl-C are given to stop their services.
STOP_WAIT_S = 30.0
#: Connection attempts when the head's client server fails to start our session's server.
CONNECT_ATTEMPTS = 3


class ClusterError(Exception):
    """Ray is not installed, or the cluster cannot be reached: one line says which."""


def check_address(address: str) -> str:
    """``address`` if it is a Ray client address (``ray://HOST:PORT``); else ValueError."""
    host, _, port = address.removeprefix("ray://").rpartition(":")
    if not address.startswith("ray://") or not host or not port.isdigit():
        raise ValueError(f"--cluster {address!r}: expected ray://HOST:PORT (the head's "
                         "client server, `ray start --head --ray-client-server-port PORT`)")
    return address


def connect(ray: Any, address: str) -> None:
    """``ray.init`` on the client ``address``, again (up to :data:`CONNECT_ATTEMPTS`) when the
    head says the server it starts for each client failed to start: once in a CI run of the
    test suite, the cause not known (the head's ``ray_client_server_*.err`` says it); a
    :class:`ClusterError` when the cluster cannot be reached."""
    for attempt in range(1, CONNECT_ATTEMPTS + 1):
        try:
            ray.init(address=address, logging_level="WARNING", log_to_driver=False)
            return
        except ConnectionError as exc:
            if "Initialization failure from server" not in str(exc) or (
                    attempt == CONNECT_ATTEMPTS):
                raise ClusterError(f"--cluster {address}: {exc}") from None
            print(f"--cluster {address}: the head could not start a client server (attempt "
                  f"{attempt} of {CONNECT_ATTEMPTS}), trying again", file=sys.stderr)
            time.sleep(2.0 * attempt)


def run_on_cluster(address: str, run: Callable[..., Any], jobs: Sequence[tuple],
                   results: list, stop: Any, interrupted: type[Exception]) -> None:
    """``run(*job)`` for every job as a Ray task of one CPU on the cluster at ``address``,
    each result appended to ``results`` as it finishes. When ``stop`` (an Event) is set,
    cancels the tasks under way and raises ``interrupted``. Raises :class:`ClusterError` when
    Ray is not installed or the cluster cannot be reached."""
    try:
        import ray
    except ImportError:
        raise ClusterError("--cluster needs Ray: pip install 'wavegrasp[cluster]'") from None
    os.environ.setdefault("RAY_USAGE_STATS_ENABLED", "0")  # nothing leaves the machine
    # Ray warns at length before it raises; the error's one line says it.
    warnings.filterwarnings("ignore", message="Ray Client connection timed out")
    connect(ray, check_address(address))
    try:
        task = ray.remote(num_cpus=1, max_retries=0)(run)
        pending = [task.remote(*job) for job in jobs]
        with tqdm(total=len(pending), desc="runs", unit="run") as bar:
            while pending:
                done, pending = ray.wait(pending, num_returns=1, timeout=0.5)
                for ref in done:
                    results.append(ray.get(ref))
                    bar.update()
                if stop.is_set():
                    for ref in pending:
                        ray.cancel(ref)  # KeyboardInterrupt in the task: it stops its services
                    if pending:  # ... before we leave: a task whose client is gone is killed
                        ray.wait(pending, num_returns=len(pending), timeout=STOP_WAIT_S)
                    raise interrupted
    finally:
        ray.shutdown()

"""Where a service process runs and how the kernel schedules it, from the environment.

A frame's way from camera to gate decision goes through the player, the router, perception, the
predictor, the planner and the gate one after the other. Those processes run under the
kernel's real-time FIFO policy (``WAVEGRASP_RT_PRIORITY``), each a step above the one before it
on the path and the router above all: a stage that receives a message runs at once, on
whichever core is free or busy with something less urgent, instead of waiting for the sender's
side work (acknowledgements, stats) or the recorder, the sim and perception's mesh worker to
yield. Those stay under the normal policy, niced and on their own CPUs.

Measured on 2 cores, camera frame to gate decision over 18 decisions each, runs alternating:
normal scheduling and the path pinned to one core, p50 19.6 ms, p99 32.2 ms; real-time FIFO,
p50 16.9 ms, p99 20.1 ms (see the README's latency section).

The compose file sets, per service, ``WAVEGRASP_CPUS`` (a Linux CPU list: from
``WAVEGRASP_HOT_CPUS``, default all, or ``WAVEGRASP_BACKGROUND_CPUS``, default ``1``; empty:
anywhere), ``WAVEGRASP_NICE`` and ``WAVEGRASP_RT_PRIORITY`` (1-99; empty: normal policy);
``WAVEGRASP_REALTIME=off`` keeps every process under the normal policy. All are applied before
any thread starts: threads inherit them.
"""

from __future__ import annotations

import contextlib
import ctypes
import os
import resource
import threading
from collections.abc import Mapping
from pathlib import Path

REALTIME_OFF = {"off", "false", "no", "0"}
REALTIME_ON = {"on", "true", "yes", "1", ""}
#: setns(2)'s flag for a network namespace.
CLONE_NEWNET = 0x40000000


def parse_cpus(text: str) -> set[int]:
    """A Linux CPU list (``"0"``, ``"0-3"``, ``"0,2-3"``) as a set; empty text: empty set.

    Raises ValueError naming the part that is not a CPU number or range.
    """
    cpus: set[int] = set()
    for part in (p.strip() for p in text.split(",")):
        if not part:
            continue
        first, sep, last = part.partition("-")
        numbers = (first, last) if sep else (first, first)
        if not all(n.strip().isdigit() for n in numbers) or int(numbers[1]) < int(numbers[0]):
            raise ValueError(f"{part!r} is not a CPU number or range (e.g. 0, 0-3, 0,2)")
        cpus.update(range(int(numbers[0]), int(numbers[1]) + 1))
    return cpus


def parse_rt_priority(text: str, realtime: str = "on") -> int | None:
    """The SCHED_FIFO priority ``text`` names (1-99), or None for the normal policy (empty
    text, or ``realtime`` off). Raises ValueError naming the variable that is malformed."""
    switch = realtime.strip().lower()
    if switch not in REALTIME_ON | REALTIME_OFF:
        raise ValueError(f"WAVEGRASP_REALTIME must be on or off, got {realtime!r}")
    if not text.strip() or switch in REALTIME_OFF:
        return None
    try:
        priority = int(text)
    except ValueError:
        priority = 0
    if not 1 <= priority <= 99:
        raise ValueError(f"WAVEGRASP_RT_PRIORITY must be an integer from 1 to 99 (or empty), "
                         f"got {text!r}")
    return priority


def place_process(env: Mapping[str, str]) -> list[str]:
    """Apply ``WAVEGRASP_NETNS`` (the network namespace), ``WAVEGRASP_NICE`` (added to the
    current nice value), ``WAVEGRASP_RT_PRIORITY`` (unless ``WAVEGRASP_REALTIME`` is off) and
    ``WAVEGRASP_CPUS`` from ``env`` to this process. Returns warnings for what this machine
    does not allow (the process then runs as it would have); raises ValueError naming a
    malformed value."""
    text = env.get("WAVEGRASP_NICE", "")
    try:
        increment = int(text or 0)
    except ValueError:
        raise ValueError(f"WAVEGRASP_NICE must be an integer, got {text!r}") from None
    try:
        wanted = parse_cpus(env.get("WAVEGRASP_CPUS", ""))
    except ValueError as exc:
        raise ValueError(f"WAVEGRASP_CPUS: {exc}") from None
    priority = parse_rt_priority(env.get("WAVEGRASP_RT_PRIORITY", ""),
                                 env.get("WAVEGRASP_REALTIME", "on"))
    if env.get("WAVEGRASP_NETNS"):
        enter_netns(env["WAVEGRASP_NETNS"])
    if increment:
        os.nice(increment)
    warnings = [realtime(priority)] if priority is not None else []
    warnings.append(pin(wanted, f"WAVEGRASP_CPUS={env.get('WAVEGRASP_CPUS', '')}"))
    return [w for w in warnings if w]


def enter_netns(name: str) -> None:
    """Move this process into the network namespace ``name`` (``ip netns``'s,
    ``/run/netns/NAME``), before any thread starts: ``wavegrasp up --tether`` runs the
    vehicle's services there. Raises ValueError naming the namespace if it cannot."""
    try:
        fd = os.open(f"/run/netns/{name}", os.O_RDONLY)
    except OSError as exc:
        raise ValueError(f"WAVEGRASP_NETNS={name}: {exc.strerror}") from None
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        if libc.setns(fd, CLONE_NEWNET) != 0:
            raise ValueError(f"WAVEGRASP_NETNS={name}: setns: "
                             f"{os.strerror(ctypes.get_errno())}")
    finally:
        os.close(fd)


def realtime(priority: int) -> str | None:
    """Run the calling thread (at start-up: the process) under SCHED_FIFO at ``priority``; a
    warning if the system does not allow it (then nothing changes)."""
    try:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(priority))
    except (OSError, AttributeError) as exc:
        return (f"WAVEGRASP_RT_PRIORITY={priority}: real-time scheduling not allowed here "
                f"({exc}; {realtime_hint(priority)}); running under the normal policy")
    return None


def realtime_hint(priority: int) -> str:
    """What this process lacks for SCHED_FIFO at ``priority``, as far as it can tell."""
    if hasattr(os, "geteuid") and os.geteuid() != 0:
        limit = resource.getrlimit(resource.RLIMIT_RTPRIO)[0]
        if limit != resource.RLIM_INFINITY and limit < priority:
            return (f"this user's rtprio limit is {limit}: raise it (compose: ulimits rtprio, "
                    "WAVEGRASP_RTPRIO_LIMIT; limits.conf) or run as root with CAP_SYS_NICE")
    try:  # cgroup v1 with real-time group scheduling: the group's own real-time budget
        group = Path("/proc/self/cgroup").read_text()
        cpu = next(line.split(":", 2)[2] for line in group.splitlines()
                   if "cpu" in line.split(":", 2)[1].split(","))
        # A container sees its own group at the hierarchy's root.
        runtime = next(p for p in (Path(f"/sys/fs/cgroup/cpu{cpu}/cpu.rt_runtime_us"),
                                   Path("/sys/fs/cgroup/cpu/cpu.rt_runtime_us")) if p.exists())
        if int(runtime.read_text()) == 0:
            return ("this cgroup has no real-time runtime (cgroup v1: dockerd --cpu-rt-runtime "
                    "and compose's cpu_rt_runtime, ops/compose-rt-cgroup-v1.yml)")
    except (OSError, ValueError, StopIteration, IndexError):
        pass
    return "it needs CAP_SYS_NICE, e.g. compose's cap_add: [SYS_NICE], or an rtprio limit"


def background_thread(nice: int, cpus: str, what: str) -> str | None:
    """Make the calling thread background work: the normal policy (a thread of a real-time
    process inherits FIFO), its own nice value and, when ``cpus`` names any it may use, its
    own CPUs. Returns a warning naming ``what`` if none of those CPUs is usable."""
    if hasattr(os, "sched_setscheduler"):
        os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))  # always allowed
    with contextlib.suppress(OSError):  # raising it is allowed; lowering it is not wanted
        os.setpriority(os.PRIO_PROCESS, threading.get_native_id(), nice)  # Linux: per thread
    return pin(parse_cpus(cpus), f"{what}={cpus}")


def pin(wanted: set[int], what: str) -> str | None:
    """Pin the calling thread (at start-up: the process, as threads inherit it) to the CPUs of
    ``wanted`` it may use; a warning naming ``what`` if there are none (then nothing changes).
    """
    if not wanted or not hasattr(os, "sched_setaffinity"):
        return None
    try:  # the kernel keeps those of them this thread may use (its cgroup's, online ones)
        os.sched_setaffinity(0, wanted)  # 0: the calling thread
    except OSError:
        return (f"{what} names no CPU this process may use ({sorted(os.sched_getaffinity(0))}); "
                "running unpinned")
    return None

"""Where a service process runs: its CPUs and its nice value, from the environment.

A frame's way from camera to gate decision goes through perception, the predictor, the planner
and the gate one after the other, never two at once, so one core serves it; what is off that
path (player, recorder, sim, perception's mesh worker) gets the other cores, and its bursts
(writing a cloud to run.mcap, a physics step) no longer land on the core a frame waits for. The
compose file sets ``WAVEGRASP_CPUS`` per service from ``WAVEGRASP_HOT_CPUS`` (default ``0``)
and ``WAVEGRASP_BACKGROUND_CPUS`` (default ``1``); an empty value leaves the process wherever
the kernel puts it. Applied before any thread starts: threads inherit both settings.
"""

from __future__ import annotations

import os


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


def place_process(nice: str, cpus: str) -> str | None:
    """Apply ``nice`` (an integer, added to the current one) and pin this process to the CPUs
    of ``cpus`` that it may use. Returns a warning when none of those CPUs is usable here (the
    process then runs anywhere); raises ValueError naming a malformed value."""
    try:
        increment = int(nice or 0)
    except ValueError:
        raise ValueError(f"WAVEGRASP_NICE must be an integer, got {nice!r}") from None
    try:
        wanted = parse_cpus(cpus)
    except ValueError as exc:
        raise ValueError(f"WAVEGRASP_CPUS: {exc}") from None
    if increment:
        os.nice(increment)
    return pin(wanted, f"WAVEGRASP_CPUS={cpus}")


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

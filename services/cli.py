"""The ``wavegrasp`` command: one sub-command per service, plus the tools around them."""

from __future__ import annotations

import importlib
import os
import re
import signal
import sys

from wavegrasp.runtime.placement import place_process

COMMANDS: dict[str, tuple[str, str]] = {
    "up": ("wavegrasp.ops.launcher", "run docker-compose.yml's services locally on a recording"),
    "router": ("wavegrasp.router.main", "the zenoh router the services connect to"),
    "player": ("wavegrasp.player.main", "replay a recording (MCAP, ROS 1 bag, ROS 2 bag)"),
    "recorder": ("wavegrasp.recorder.main", "record every message on the bus to run.mcap"),
    "edge": ("wavegrasp.edge.main", "on the vehicle: camera clouds cut down to what the "
             "tether carries"),
    "perception": ("wavegrasp.perception.main", "point clouds -> the object's centroid and mesh"),
    "predictor": ("wavegrasp.predictor.main", "centroids -> the object's motion a period ahead"),
    "planner": ("wavegrasp.planner.main", "predictions -> a grasp and its timed trajectory"),
    "gate": ("wavegrasp.gate.main", "plans -> go / no-go (prediction error, freshness, health)"),
    "sim": ("wavegrasp.sim.main", "PyBullet executes approved plans and judges each grasp"),
    "foxglove": ("wavegrasp.foxglove.main", "the bus live for Foxglove (WebSocket, "
                 "127.0.0.1:8765)"),
    "scene": ("wavegrasp.scene.main", "the grasp as Foxglove and rviz2 draw it: /tf, "
              "robot_description, markers"),
    "eval": ("wavegrasp.ops.experiment", "the paper's experiment: trials per predictor and "
             "configuration"),
    "viewer": ("wavegrasp.ops.viewer", "rerun's web viewer, fed live by the recorder"),
    "latency": ("wavegrasp.ops.latency", "per-hop and end-to-end latency of a run, from its "
                "traces"),
    "replan": ("wavegrasp.ops.replan", "the planner of today's code again on a run's own "
               "messages: what it plans, prediction by prediction"),
    "faults": ("wavegrasp.ops.faults", "run the pipeline, inject faults (bad input, crashes, "
               "bad files) and report what survived"),
    "soak": ("wavegrasp.ops.soak", "run a recording looped for a long while and watch every "
             "service's memory and every frame"),
    "record": ("wavegrasp.wavetank.record", "generate a wave-tank recording from physics"),
    "health": ("wavegrasp.ops.health", "exit 0 if a service's liveliness token is up"),
    "keys": ("wavegrasp.ops.keys", "this installation's logins and TLS certificates for "
             "access control on the bus"),
}


#: The commands that run a service loop (:class:`wavegrasp.runtime.service.Service`).
SERVICES = {"player", "edge", "foxglove", "scene", "recorder", "perception", "predictor",
            "planner", "gate", "sim"}


#: One thread per process for the numeric libraries unless the user says otherwise. A pipeline
#: is about nine processes on a few cores: OpenBLAS's and OpenMP's worker threads spin while
#: they wait, and measured on 2 cores they cost more than they gave (the blend predictor used
#: 18.9 s of CPU on a 135 s lockstep run with them, 3.8 s without; two recordings generated
#: side by side took 41 s with them, 17 s without).
THREAD_LIMITS = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")


def usage() -> str:
    lines = ["usage: wavegrasp COMMAND [ARGS]", "", "commands:"]
    lines += [f"  {name:10s} {help_}" for name, (_, help_) in COMMANDS.items()]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if not argv or argv[0] in ("-h", "--help"):
        print(usage())
        return 0 if argv else 2
    name, rest = argv[0], argv[1:]
    if name not in COMMANDS:
        print(f"wavegrasp: unknown command {name!r}\n\n{usage()}", file=sys.stderr)
        return 2
    for var in THREAD_LIMITS:  # read when numpy and open3d load, so before any import
        os.environ.setdefault(var, "1")
    if name in SERVICES or name == "router":
        # Before any thread starts (threads inherit all of it): the camera-to-decision path
        # runs real-time, what is off it yields.
        try:
            warnings = place_process(os.environ)
        except ValueError as exc:
            print(f"wavegrasp {name}: {exc}", file=sys.stderr)
            return 2
        for warning in warnings:
            print(f"wavegrasp {name}: warning: {warning}", file=sys.stderr)
    if name in SERVICES:
        # Block the stop signals before any library starts a thread (threads inherit the
        # mask): the service loop then takes them with sigtimedwait, whichever thread the
        # kernel would have picked and whatever handler a library installed.
        signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT, signal.SIGTERM})
    try:  # open3d and PyBullet load on import, some commands import them late
        module = importlib.import_module(COMMANDS[name][0])
        return int(module.main(rest) or 0)
    except (ImportError, OSError) as exc:
        missing = system_library(exc)
        if missing is None:
            raise
        print(f"wavegrasp {name}: the system library {missing} is missing (open3d and "
              f"PyBullet need it): install it, e.g. `sudo apt-get install "
              f"{APT_PACKAGES.get(missing.split('.so')[0], '<its package>')}`, or run "
              "`bash ops/setup.sh`", file=sys.stderr)
        return 2


#: Debian's packages of the system libraries our wheels load (open3d's above all).
APT_PACKAGES = {"libusb-1.0": "libusb-1.0-0", "libgomp": "libgomp1", "libGL": "libgl1",
                "libEGL": "libegl1", "libX11": "libx11-6", "libstdc++": "libstdc++6"}


def system_library(exc: BaseException) -> str | None:
    """The shared library an import could not load (``libusb-1.0.so.0``), if that is what
    ``exc`` says."""
    match = re.search(r"(lib[\w.+-]+\.so[\w.]*): cannot open shared object file", str(exc))
    return match.group(1) if match else None

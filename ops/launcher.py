"""``wavegrasp up [RECORDING]``: run docker-compose.yml's services as local processes.

Starts the services in dependency order (the router first), waits for each dependency's
liveliness token where compose asks for ``service_healthy``, prefixes every log line with the
service's name, and stops everything, in reverse order, when a service labelled
``wavegrasp.ends-run`` finishes (the player at the recording's end, or the sim after its
last trial when asked to), when one crashes, or on Ctrl-C. Writes
``OUT/run.mcap`` (through the recorder) and ``OUT/summary.json``. Exit code: 0 when the run
completed, 1 when a service crashed, 2 for bad arguments, 130 after Ctrl-C.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import queue
import signal
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Mapping
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import TextIO

from wavegrasp.ops import forked
from wavegrasp.ops.choices import check_choices
from wavegrasp.ops.compose import ComposeService, load_compose, start_order
from wavegrasp.ops.sample import default_recording, project_root
from wavegrasp.ops.status import Progress
from wavegrasp.ops.tether import CLOUD_SHARE, VEHICLE, Tether, across_tether
from wavegrasp.ops.viewer import viewer_url
from wavegrasp.predictor import DEFAULT_MODEL
from wavegrasp.recorder.summary import RunSummary
from wavegrasp.recording_io.reader import (
    RecordingError,
    check_camera_transform,
    open_for_replay,
)
from wavegrasp.runtime.bus import Bus, Delivery, remove_orphaned_segments
from wavegrasp.runtime.settings import Settings
from wavegrasp.schemas import (
    CLOCK_KEY,
    Clock,
    GateDecision,
    GraspOutcome,
    PlayerStatus,
    ServiceStats,
)

STOP_TIMEOUT_S = 10.0
#: The edge stage's clouds, which cross a tether instead of the camera's.
EDGE_POINTS_KEY = "wavegrasp/edge/points"
#: As compose restarts a service: after 100 ms, doubling with each restart in a row, reset once
#: it has stayed up this long.
RESTART_DELAY_S = 0.1
RESTART_DELAY_MAX_S = 10.0
RESTART_STABLE_S = 10.0
#: The status line: redrawn this often on a terminal; elsewhere a plain line this often.
STATUS_PERIOD_S = 0.5
PLAIN_STATUS_PERIOD_S = 10.0
CLEAR = "\r\x1b[K"  # back to the line's start and clear it


@dataclass
class Restart:
    """A service that failed and was started again; seconds since the run started."""

    exit_code: int
    died_s: float
    restarted_s: float | None = None
    back_s: float | None = None  # its liveliness token is up again


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def local_command(command: list[str]) -> list[str]:
    """The compose command as a local process: ``wavegrasp ...`` runs this interpreter's."""
    if command and command[0] == "wavegrasp":
        return [sys.executable, "-m", "wavegrasp", *command[1:]]
    return command


class Launcher:
    def __init__(self, services: dict[str, ComposeService], env: dict[str, str],
                 fork: bool = True, log: TextIO | None = None,
                 interrupted: threading.Event | None = None) -> None:
        self.services = services
        self.env = env
        self.fork = fork  # services forked from a process with their libraries loaded
        self.stream = log or sys.stdout  # every service's lines and the launcher's own
        if fork:
            forked.prepare()
        self.order = start_order(services)
        self.procs: dict[str, subprocess.Popen[bytes] | forked.ForkedService] = {}
        self.started: list[str] = []
        self.bus: Bus | None = None
        self.summary = RunSummary()
        self.interrupted = interrupted or threading.Event()  # set: the run stops
        self.killed: list[str] = []  # services that ignored SIGTERM and had to be killed
        self.restarts: dict[str, list[Restart]] = {}
        self._pumps: list[threading.Thread] = []
        self._t0 = time.monotonic()
        self._up_since: dict[str, float] = {}
        self._delay: dict[str, float] = {}
        self._due: dict[str, float] = {}  # restarts waiting for their delay
        self.progress = Progress()
        #: A terminal gets a status line kept under the services' lines.
        self.live = self.stream.isatty()
        self._status = ""  # the status line shown now (a terminal's)
        self._status_at = 0.0
        self._write = threading.Lock()  # the pumps' threads and the main one write

    def log(self, text: str, name: str = "up") -> None:
        with self._write:
            self.stream.write(f"{CLEAR if self._status else ''}{name:>10} | {text}\n"
                              f"{self._status}")
            self.stream.flush()

    def show_status(self) -> None:
        """The status line: kept at the bottom of a terminal (redrawn every
        STATUS_PERIOD_S), elsewhere a plain line every PLAIN_STATUS_PERIOD_S."""
        now = time.monotonic()
        period = STATUS_PERIOD_S if self.live else PLAIN_STATUS_PERIOD_S
        if now - self._status_at < period:
            return
        self._status_at = now
        line = self.progress.line(self.summary)
        if not self.live:
            self.log(line, "status")
            return
        with self._write:
            self._status = line
            self.stream.write(f"{CLEAR}{line}")
            self.stream.flush()

    def clear_status(self) -> None:
        with self._write:
            if self._status:
                self.stream.write(CLEAR)
                self.stream.flush()
            self._status = ""

    def _pump(self, name: str, stream) -> None:
        for raw in iter(stream.readline, b""):
            self.log(raw.decode(errors="replace").rstrip(), name)

    def start(self, name: str) -> None:
        svc = self.services[name]
        env = {**os.environ, **self.env, **svc.environment, "PYTHONUNBUFFERED": "1"}
        command = local_command(svc.command)
        args = forked.forkable(command, env) if self.fork else None
        proc = forked.ForkedService(args, env) if args else subprocess.Popen(
            command, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
            start_new_session=True)
        self.procs[name] = proc
        self._up_since[name] = time.monotonic()
        if name not in self.started:
            self.started.append(name)
        pump = threading.Thread(target=self._pump, args=(name, proc.stdout), daemon=True)
        pump.start()
        self._pumps.append(pump)

    def connect(self) -> None:
        settings = Settings.from_env("launcher", env=self.env, connect_timeout_s=20.0,
                                  shared_memory_mb=0)  # it sends nothing large
        self.bus = Bus(settings)
        self.bus.watch_alive()
        self.bus.subscribe("wavegrasp/*/stats", self.on_stats, ServiceStats)
        self.bus.subscribe("wavegrasp/player/status", self.on_status, PlayerStatus)
        self.bus.subscribe("wavegrasp/sim/outcome", self.on_outcome, GraspOutcome)
        self.bus.subscribe(CLOCK_KEY, lambda msg, _d: self.progress.on_clock(msg), Clock)
        self.bus.subscribe("wavegrasp/gate/decision",
                           lambda msg, _d: self.progress.on_decision(msg), GateDecision)

    def on_outcome(self, msg: GraspOutcome, _d: Delivery) -> None:
        self.summary.on_outcome(msg)
        self.log(f"grasp attempt {msg.attempt} ({msg.plan_id}): "
                 + ("success" if msg.success else f"aborted, {msg.evidence.get('reason')}"
                    if msg.aborted else f"failed, {msg.failure}"))

    def on_stats(self, msg: ServiceStats, _d: Delivery) -> None:
        self.summary.on_stats(msg)

    def on_status(self, msg: PlayerStatus, _d: Delivery) -> None:
        self.summary.on_status(msg)

    def pump_bus(self) -> None:
        while self.bus is not None:
            try:
                self.bus.dispatch(self.bus.inbox.get_nowait())
            except queue.Empty:
                return

    def crashed(self) -> list[str]:
        return [n for n, p in self.procs.items() if p.poll() not in (None, 0)]

    def now_s(self) -> float:
        return time.monotonic() - self._t0

    def handle_failures(self) -> bool:
        """Restart failed services as their compose ``restart`` policy says (after compose's
        delay); False if one failed that may not be restarted."""
        now = time.monotonic()
        for name in self.crashed():
            if name in self._due:
                continue
            code = self.procs[name].returncode
            history = self.restarts.setdefault(name, [])
            if not self.services[name].restarts_after(code, len(history)):
                return False
            if now - self._up_since[name] >= RESTART_STABLE_S:
                self._delay[name] = RESTART_DELAY_S
            delay = self._delay.get(name, RESTART_DELAY_S)
            self._delay[name] = min(2 * delay, RESTART_DELAY_MAX_S)
            self._due[name] = now + delay
            history.append(Restart(code, round(self.died_s(name), 3)))
            self.log(f"{name} exited with code {code}: restarting it in {delay:.1f} s "
                     f"(restart {len(history)})")
        for name, due in list(self._due.items()):
            if now >= due:
                del self._due[name]
                self.restarts[name][-1].restarted_s = round(self.now_s(), 3)
                self.start(name)
        self.note_back()
        return True

    def died_s(self, name: str) -> float:
        """When ``name``'s failed process died, seconds since the run started: when its own
        liveliness token went (the router sees a killed process's link close at once), not
        when this loop, busy with the bus, noticed the exit; now if no token of it went."""
        now = self.now_s()
        gone = self.bus.gone_since.get(name) if self.bus is not None else None
        if gone is None or gone < self._up_since[name]:
            return now
        return min(now, gone - self._t0)

    def note_back(self) -> None:
        """Stamp each restarted service's return: its liveliness token is up again."""
        if self.bus is None:
            return
        alive = self.bus.alive_now()
        for name, history in self.restarts.items():
            last = history[-1] if history else None
            if not (last and last.restarted_s is not None and last.back_s is None):
                continue
            # A process's own token that appeared after the restart: the dead one's service
            # token may linger a moment, and hides the new one's while it does.
            since = self.bus.alive_since.get(name, -1.0) - self._t0
            if name in alive and since >= last.restarted_s:
                last.back_s = round(since, 3)
                self.log(f"{name} is back {last.back_s - last.died_s:.1f} s after it died")

    def wait_healthy(self, names: list[str], timeout_s: float = 30.0) -> bool:
        assert self.bus is not None
        deadline = time.monotonic() + timeout_s
        missing = set(names)
        while missing and time.monotonic() < deadline and not self.interrupted.is_set():
            if self.crashed():
                return False
            missing = self.bus.wait_for_services(sorted(missing), 0.5)
        if missing:
            self.log(f"not healthy after {timeout_s:.0f} s: {', '.join(sorted(missing))}")
        return not missing

    def bring_up(self) -> bool:
        for name in self.order:
            healthy = [d for d, c in self.services[name].depends_on.items()
                       if c == "service_healthy"]
            if self.bus is None and self.started and (
                    "router" in self.started or "router" not in self.services):
                self.connect()  # to the router (the topside's, with a tether)
            if healthy and not self.wait_healthy(healthy):
                return False
            if self.interrupted.is_set():
                return False
            self.start(name)
        if self.bus is None:
            self.connect()
        return True

    def wait_end(self) -> str:
        """Block until the run ends; returns why: finished, crashed or interrupted."""
        enders = [n for n, s in self.services.items() if s.labels.get("wavegrasp.ends-run")]
        while not self.interrupted.is_set():
            self.pump_bus()
            self.show_status()
            if not self.handle_failures():
                return "crashed"
            if any(self.procs[n].poll() == 0 for n in enders):
                return "finished"
            time.sleep(0.05)
        return "interrupted"

    def stop_all(self) -> None:
        """Stop the services together (each notices SIGTERM within a turn of its loop, about
        0.1 s: one by one, a run's eight took 0.6 s), then those labelled
        wavegrasp.stop-late (the recorder: it records the others' last counters), the routers,
        and those labelled wavegrasp.stop-last (the viewer), which outlive what feeds them."""
        def labelled(label: str) -> list[str]:
            return [n for n in self.started if self.services[n].labels.get(label)]

        late, last = labelled("wavegrasp.stop-late"), labelled("wavegrasp.stop-last")
        # The vehicle's router too (a tether): the last counters of its services cross it.
        routers = [n for n in self.started if n in ("router", "vehicle-router")]
        first = [n for n in reversed(self.started) if n not in {*late, *last, *routers}]
        self.stop_together(first)
        self.stop_together(late)
        if routers:
            if self.bus is not None:
                self.pump_bus()
                self.bus.close()
                self.bus = None
            self.stop_together(routers)
        self.stop_together(last)
        if self.bus is not None:
            self.bus.close()
            self.bus = None
        for pump in self._pumps:
            pump.join(timeout=2.0)
        remove_orphaned_segments()  # the services' own, and those of any that was killed

    def stop_together(self, names: list[str]) -> None:
        """SIGTERM to each of ``names`` at once, then wait for each; a service that ignores
        it gets it again, then SIGKILL after STOP_TIMEOUT_S (its stacks logged first)."""
        running = [n for n in names if self.procs[n].poll() is None]
        for name in running:
            signal_group(self.procs[name].pid, signal.SIGTERM)
        for name in running:
            proc = self.procs[name]
            try:
                proc.wait(STOP_TIMEOUT_S / 2)
            except subprocess.TimeoutExpired:
                # Seen rarely: a SIGTERM that never reaches the service's handler.
                self.log(f"{name} still running after SIGTERM: sending it again")
                signal_group(proc.pid, signal.SIGTERM)
            try:
                proc.wait(STOP_TIMEOUT_S / 2)
            except subprocess.TimeoutExpired:
                self.log(f"{name} did not stop in {STOP_TIMEOUT_S:.0f} s: killing it")
                self.killed.append(name)
                with contextlib.suppress(ProcessLookupError):
                    os.kill(proc.pid, signal.SIGUSR1)  # its stacks, into its log
                time.sleep(0.5)
                os.killpg(proc.pid, signal.SIGKILL)
                proc.wait()
        for name in names:
            with contextlib.suppress(ProcessLookupError):  # anything the service started
                os.killpg(self.procs[name].pid, signal.SIGKILL)


def signal_group(pid: int, sig: int) -> None:
    """``sig`` to the process group a service leads, or to the service alone while it has not
    made its group yet (stopped right after its start: a forked one makes it first thing)."""
    try:
        os.killpg(pid, sig)
    except ProcessLookupError:
        with contextlib.suppress(ProcessLookupError):
            os.kill(pid, sig)


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(prog="wavegrasp up", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("recording", nargs="?", type=Path,
                        help="MCAP, ROS 1 .bag or ROS 2 bag folder (default: the sample)")
    parser.add_argument("--pace", choices=["realtime", "fast", "lockstep"], default="realtime")
    parser.add_argument("--predictor",
                        help=f"motion model for the predictor service (default {DEFAULT_MODEL})")
    parser.add_argument("--out", type=Path, help="run folder (default: runs/<date-time>)")
    parser.add_argument("--compose", type=Path, help="compose file (default: docker-compose.yml)")
    parser.add_argument("--viewer", action="store_true",
                        help="also run rerun's web viewer (the compose file's viewer profile), "
                        "fed live; it stays up after the run until Ctrl-C")
    parser.add_argument("--viewer-port", type=int, default=9090,
                        help="HTTP port of the web viewer (default 9090)")
    parser.add_argument("--scene", action="store_true",
                        help="also draw the grasp for Foxglove and rviz2 (/tf, "
                        "robot_description, markers; the compose file's scene profile), "
                        "recorded in run.mcap")
    parser.add_argument("--foxglove", action="store_true",
                        help="also serve the bus live for Foxglove (the compose file's "
                        "foxglove profile, with the scene) on 127.0.0.1:--foxglove-port")
    parser.add_argument("--foxglove-port", type=int, default=8765,
                        help="its WebSocket port (default 8765)")
    parser.add_argument("--tether", type=float, metavar="MBIT",
                        help="the vehicle's services (player, sim) and a router of their own "
                        "in a network namespace, joined to the topside's by a link of MBIT "
                        "Mbit/s each way (needs root; ops/tether.py)")
    parser.add_argument("--no-fork", dest="fork", action="store_false",
                        help="start each service as a command of its own (as compose does), "
                        "not forked from a process that has loaded their libraries once")
    return parser.parse_args(argv)


@dataclass
class Run:
    """A run being set up or under way: what ``wavegrasp up`` was asked for."""

    args: argparse.Namespace
    launcher: Launcher
    env: dict[str, str]
    out: Path
    recording: Path
    started: float = 0.0
    crashed: list[str] = field(default_factory=list)
    tether: Tether | None = None


def prepare(args: argparse.Namespace, environ: Mapping[str, str] | None = None,
            log: TextIO | None = None, interrupted: threading.Event | None = None) -> Run:
    """Check the arguments and read the compose file; raises ValueError saying what is wrong.
    ``environ``: where the WAVEGRASP_ and ZENOH_ settings come from (default this process's
    environment); ``log`` and ``interrupted``: the :class:`Launcher`'s."""
    environ = os.environ if environ is None else environ
    root = project_root()
    compose_path = args.compose or (Path.cwd() / "docker-compose.yml")
    if not compose_path.exists():
        compose_path = root / "docker-compose.yml"
    out = (args.out or Path("runs") / time.strftime("%Y%m%d-%H%M%S")).resolve()
    if (out / "run.mcap").exists():
        raise ValueError(f"{out} already holds run.mcap: choose another --out")
    recording = args.recording or default_recording()
    try:  # before anything starts: a bad file gets one line, not a pipeline that fails
        opened = open_for_replay(recording)
        check_camera_transform(opened)
        problem = opened.problem
    except RecordingError as exc:
        raise ValueError(str(exc)) from None
    check_choices(args, environ)
    if problem:  # e.g. cut short: the player replays what is readable
        print(f"wavegrasp up: warning: {recording}: {problem}", file=sys.stderr)
    env = {
        "WAVEGRASP_ROUTER_HOST": "127.0.0.1", "WAVEGRASP_ROUTER_BIND": "127.0.0.1",
        "WAVEGRASP_ROUTER_PORT": str(free_port()),
        **{k: v for k, v in environ.items() if k.startswith(("WAVEGRASP_", "ZENOH_"))},
        "WAVEGRASP_RECORDING": str(recording.resolve()), "WAVEGRASP_OUT": str(out),
        "WAVEGRASP_PACE": args.pace,
        "WAVEGRASP_PLAYER_RESUME_FILE": str(out / "player-position.json"),
        "WAVEGRASP_SIM_RESUME_FILE": str(out / "sim-state.json"),
    }
    # docker-compose.yml turns access control on (ZENOH_CONFIG, the logins its router makes
    # in WAVEGRASP_KEYS); here, on the loopback, the bus stays open unless ZENOH_CONFIG names
    # the logins (and the router makes none unless WAVEGRASP_KEYS names a folder).
    env["WAVEGRASP_ZENOH_CONFIG"] = environ.get("ZENOH_CONFIG", "")
    env.setdefault("WAVEGRASP_KEYS", "")
    if args.pace != "realtime":
        # Real-time priorities serve latency at the recording's rate. Faster, the path's
        # services would take both cores from the recorder and the sim that the run waits
        # for: the sample played in 15.3 s at fast pace with them, 10.4 s without.
        env.setdefault("WAVEGRASP_REALTIME", "off")
    if args.predictor:
        env["WAVEGRASP_PREDICTOR"] = args.predictor
    if args.viewer:
        grpc_port = free_port()
        env |= {"WAVEGRASP_VIEWER_BIND": "127.0.0.1", "WAVEGRASP_VIEWER_GRPC_PORT": str(grpc_port),
                "WAVEGRASP_VIEWER_WEB_PORT": str(args.viewer_port),
                "WAVEGRASP_VIEWER_URL": f"rerun+http://127.0.0.1:{grpc_port}/proxy"}
    env["ZENOH_CONNECT"] = f"tcp/127.0.0.1:{env['WAVEGRASP_ROUTER_PORT']}"
    tether = None
    if args.tether is not None:
        tether = Tether(args.tether)
        tether.check()
        # No shared-memory pool: a frame in it would reach the topside past the tether.
        env["WAVEGRASP_SHARED_MEMORY_MB"] = "0"
        # The edge stage's clouds cross it, the camera's own stay on the vehicle.
        env["WAVEGRASP_POINTS_KEY"] = EDGE_POINTS_KEY
        env.setdefault("WAVEGRASP_EDGE_MBIT", f"{CLOUD_SHARE * args.tether:g}")
    profiles = {"viewer"} if args.viewer else set()
    if args.scene:
        profiles.add("scene")
    if args.foxglove:
        profiles.add("foxglove")
        env |= {"WAVEGRASP_FOXGLOVE_HOST": "127.0.0.1",
                "WAVEGRASP_FOXGLOVE_PORT": str(args.foxglove_port)}
    services = load_compose(compose_path, env, frozenset(
        profiles | {"edge"} if tether is not None else profiles))
    if tether is not None:
        across_tether(services, tether, free_port())
    out.mkdir(parents=True, exist_ok=True)
    launcher = Launcher(services, env, args.fork, log, interrupted)
    launcher.progress.start_ns, launcher.progress.end_ns = opened.start_ns, opened.end_ns
    loops = env.get("WAVEGRASP_LOOPS", "1")
    if opened.start_ns and opened.end_ns and loops.isdigit() and int(loops) > 1:
        # The player's loops follow one another: about as long again each.
        launcher.progress.end_ns = opened.start_ns + int(loops) * (opened.end_ns
                                                                  - opened.start_ns)
    return Run(args, launcher, env, out, recording, tether=tether)


def execute(run: Run) -> str:
    """Bring the services up, wait for the run's end and stop them; returns why it ended."""
    launcher, args = run.launcher, run.args
    run.started = time.time()
    if run.tether is not None:
        try:
            run.tether.__enter__()
        except (OSError, ValueError) as exc:
            launcher.log(f"cannot make the tether: {exc}")
            return "crashed"
        launcher.log(f"tether: {run.tether.mbit:g} Mbit/s each way, the vehicle's services "
                     f"({', '.join(VEHICLE)}) in network namespace {run.tether.name}")
    launcher.log(f"recording {run.recording} -> {run.out} ({args.pace})")
    if not run.env["WAVEGRASP_ZENOH_CONFIG"]:
        launcher.log("the bus is open on the loopback (access control: `wavegrasp keys`, then "
                     "ZENOH_CONFIG=\"$PWD/keys/{service}.json5\" wavegrasp up)")
    try:
        why = launcher.wait_end() if launcher.bring_up() else "crashed"
        if launcher.interrupted.is_set():
            why = "interrupted"
        elif args.viewer and "viewer" in launcher.procs:
            grpc_port = int(run.env["WAVEGRASP_VIEWER_GRPC_PORT"])
            launcher.log(f"{why}; the viewer stays up at "
                         f"{viewer_url(args.viewer_port, grpc_port)} until Ctrl-C")
            launcher.interrupted.wait()
    finally:
        launcher.clear_status()
        run.crashed = launcher.crashed()
        launcher.stop_all()
        run.crashed += launcher.killed
        if run.tether is not None:
            run.tether.__exit__()
    return why


def summarize(run: Run, why: str) -> dict:
    """Write ``summary.json`` and log the run's end; returns the summary."""
    launcher = run.launcher
    codes = {n: p.returncode for n, p in launcher.procs.items()}
    collected = launcher.summary
    summary = {
        "recording": str(run.recording), "pace": run.args.pace, "out": str(run.out),
        "ended": why, "crashed": run.crashed, "exit_codes": codes,
        "duration_s": round(time.time() - run.started, 3), **collected.as_dict(),
        "restarts": {n: [asdict(r) for r in rs] for n, rs in launcher.restarts.items() if rs},
        "files": sorted(p.name for p in run.out.glob("run*.mcap")),
        "gate": launcher.progress.gate(),
    }
    if run.tether is not None:
        summary["tether"] = run.tether.traffic()
        launcher.log(f"tether: {summary['tether']}")
    (run.out / "summary.json").write_text(json.dumps(summary, indent=2) + "\n")
    for name, per_key in summary["bad_messages"].items():
        reasons = collected.stats[name].get("last_bad_reason", {})
        for key, n in sorted(per_key.items()):
            launcher.log(f"bad messages: {name} <- {key}: {n} (last: {reasons.get(key, '?')})")
    for name, rs in launcher.restarts.items():
        backs = [f"{r.back_s - r.died_s:.1f} s" if r.back_s is not None else "not back"
                 for r in rs]
        launcher.log(f"restarted {name} {len(rs)} time(s); back after {', '.join(backs)}")
    grasps = collected.outcome_kinds() or "none"
    restarts = {n: len(rs) for n, rs in launcher.restarts.items() if rs}
    launcher.stream.write(launcher.progress.table(collected, restarts, run.out) + "\n")
    launcher.log(f"{why}: {collected.player_status.get('frames', 0)} frames, "
                 f"{collected.bad_total()} bad messages; grasps {grasps};"
                 f" exit codes {codes}; wrote {run.out / 'summary.json'}")
    return summary


def exit_code(run: Run, why: str) -> int:
    if why == "interrupted":
        return 130
    return 1 if run.crashed or why == "crashed" else 0


def up(argv: list[str], environ: Mapping[str, str] | None = None, log: TextIO | None = None,
       interrupted: threading.Event | None = None) -> int:
    """``wavegrasp up ARGV`` in this process, its settings from ``environ``, its lines to
    ``log``, stopped when ``interrupted`` is set; returns its exit code. Its services are
    forked from this process's fork server, which loads their libraries once for every run
    this process makes (``wavegrasp eval``: 1.1 CPU s a run)."""
    args = parse_args(argv)
    try:
        run = prepare(args, environ, log, interrupted)
    except ValueError as exc:
        print(f"wavegrasp up: {exc}", file=log or sys.stderr, flush=True)
        return 2
    why = execute(run)
    summarize(run, why)
    return exit_code(run, why)


def main(argv: list[str] | None = None) -> int:
    interrupted = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: interrupted.set())
    return up(sys.argv[1:] if argv is None else argv, interrupted=interrupted)

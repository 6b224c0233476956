"""``wavegrasp faults [RECORDING]``: run the pipeline, break it on purpose, say what survived.

Runs ``wavegrasp up --pace realtime`` on RECORDING (default: a 40 s wave-tank recording,
generated once into the cache) and, while it runs:

1. **bad input**: every kind of malformed payload in :data:`BAD_INPUTS` on every key each
   service subscribes to (read from the services' own stats); survived when every service
   counted each one as bad and none died;
2. **crashes**: SIGKILL to each service in turn (``--kill``), waiting for the launcher to
   restart it; survived when it is back (its liveliness token up) within 5 s. Lost: camera
   frames the service never acknowledged between its death and a second after its return;
   for the recorder, also the seconds of the run missing from its files.
3. **bad files**: the player on random bytes, a text file and an MCAP header with nothing
   after it; survived when it exits with one clear line naming the file and no traceback.
4. with ``--tether MBIT`` (``wavegrasp up --tether``; then no kills unless ``--kill`` names
   some): **tether cuts** of 2 s, 0.3 s after the arm begins to execute an approved plan and
   then while the arm is idle; survived when the arm's side stopped within its watchdog time
   (the sim's own count of the time since the last heartbeat), and every service was heard
   from again after the link returned; the run must end with a grasp.

Then it checks the gate approved nothing while an upstream service was down, prints a table
and writes ``OUT/faults.json`` beside the run's ``summary.json``. Exit code 0 when everything
survived, 1 otherwise.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import math
import os
import queue
import signal
import subprocess
import sys
import threading
import time
from collections import defaultdict
from dataclasses import asdict, dataclass, field
from pathlib import Path

from wavegrasp.ops import launcher as up
from wavegrasp.ops.sample import cached_recording
from wavegrasp.recording_io.reader import RecordingError, read_mcap
from wavegrasp.runtime.bus import CDR, JSON, Bus, Delivery
from wavegrasp.runtime.settings import Settings
from wavegrasp.schemas import (
    ROS_KEYS,
    ArmState,
    Clock,
    FrameAck,
    GateDecision,
    GraspOutcome,
    ServiceStats,
)

#: Malformed payloads by kind: what a stray or broken publisher could send.
BAD_INPUTS: dict[str, bytes] = {
    "random bytes": bytes(range(256))[::7] * 3,
    "JSON of the wrong type": b'{"header": "not a header", "seq": [1, 2]}',
    "JSON missing fields": b"{}",
    "NaN and inf": b'{"header": {"seq": 1, "stamp_ns": NaN}, "x": Infinity}',
    "empty": b"",
}
KILL_ORDER = ["perception", "predictor", "planner", "gate", "sim", "recorder", "player",
              "router"]
BACK_WITHIN_S = 5.0
WAIT_BACK_S = 15.0  # the longest a killed service is waited for before the next kill
FRAMES_KEY = "trisect/points"
#: A tether cut: how long, and how long after the arm begins a plan it comes in an approach.
CUT_S = 2.0
CUT_AFTER_START_S = 0.3
#: The sim's watchdog time (SimSettings.watchdog_s, unless WAVEGRASP_WATCHDOG_S says).
WATCHDOG_S = float(os.environ.get("WAVEGRASP_WATCHDOG_S", "0.5"))
STOPS = "watchdog: stopped, no heartbeat"
STOP_MS = "watchdog: the last stop, ms after the last heartbeat"
REFUSED_CUT = "paths refused: no heartbeat"
REFUSED_STALE = "paths refused: stale"
SIM_WATCH = (STOPS, REFUSED_CUT, REFUSED_STALE)


@dataclass
class Fault:
    """One injected fault and what came of it. Times: seconds since the run started."""

    kind: str
    target: str
    at_s: float
    survived: bool = False
    back_after_s: float | None = None
    lost: str = ""
    lost_s: float | None = None  # the recorder: seconds of written data its kill lost
    detail: str = ""


@dataclass
class Down:
    """A killed service's time down, monotonic seconds; ``back`` None while it is not back
    (it may never be: the run can end first)."""

    name: str
    fault: Fault
    died: float
    back: float | None = None

    def until(self) -> float:
        """When it came back, or the longest the injector waits for it."""
        return self.back if self.back is not None else self.died + WAIT_BACK_S


@dataclass
class Watch:
    """What the injector's own session sees: frames published over time, each service's frame
    acknowledgements, gate decisions and the services' stats."""

    frames: list[tuple[float, int]] = field(default_factory=list)  # (monotonic, published)
    acks: dict[str, set[int]] = field(default_factory=lambda: defaultdict(set))
    gos: list[float] = field(default_factory=list)  # monotonic times of go decisions
    approaches: list[float] = field(default_factory=list)  # of them, a plan's first
    outcomes: list[float] = field(default_factory=list)  # monotonic times of grasp outcomes
    #: The plans the arm began to execute, in order (from its state's executing_plan_id).
    executed: list[str] = field(default_factory=list)
    stats: dict[str, ServiceStats] = field(default_factory=dict)
    stats_at: dict[str, float] = field(default_factory=dict)  # monotonic, the latest's arrival

    def on_clock(self, msg: Clock, _d: Delivery) -> None:
        if FRAMES_KEY in msg.published:
            self.frames.append((time.monotonic(), msg.published[FRAMES_KEY]))

    def on_ack(self, msg: FrameAck, _d: Delivery) -> None:
        self.acks[msg.service].add(msg.frame_seq)

    def on_decision(self, msg: GateDecision, _d: Delivery) -> None:
        if msg.go:
            self.gos.append(time.monotonic())
            if msg.reason != "go: update":
                self.approaches.append(time.monotonic())

    def on_arm_state(self, msg: ArmState, _d: Delivery) -> None:
        plan = msg.executing_plan_id
        if plan and (not self.executed or self.executed[-1] != plan):
            self.executed.append(plan)

    def on_outcome(self, _msg: GraspOutcome, _d: Delivery) -> None:
        self.outcomes.append(time.monotonic())

    def on_stats(self, msg: ServiceStats, _d: Delivery) -> None:
        self.stats[msg.service] = msg
        self.stats_at[msg.service] = time.monotonic()

    def counter(self, service: str, name: str) -> int:
        stats = self.stats.get(service)
        return int(stats.counters.get(name, 0)) if stats is not None else 0

    def frames_between(self, t0: float, t1: float) -> range:
        """Sequence numbers of the camera frames published between two monotonic times."""
        before = [n for t, n in self.frames if t <= t0]
        upto = [n for t, n in self.frames if t <= t1]
        return range(before[-1] if before else 0, upto[-1] if upto else 0)


class Injector:
    """Drives the faults from its own thread while the launcher runs the pipeline."""

    def __init__(self, run: up.Run, kill: list[str], pause_s: float) -> None:
        self.run, self.kill, self.pause_s = run, kill, pause_s
        self.faults: list[Fault] = []
        self.watch = Watch()
        self.bus: Bus | None = None
        self.sent: dict[tuple[str, str], int] = defaultdict(int)  # (service, key) -> payloads
        self.down: list[Down] = []  # one per kill, made as it is killed
        self.counted: dict[str, dict[str, int]] = {}  # service -> bad per key, after the input

    def now_s(self) -> float:
        return self.run.launcher.now_s()

    def connect(self) -> Bus:
        bus = Bus(Settings.from_env("fault-injector", env=self.run.env, connect_timeout_s=30))
        w = self.watch
        bus.subscribe("wavegrasp/clock", w.on_clock, Clock)
        bus.subscribe("wavegrasp/*/ack", w.on_ack, FrameAck)
        bus.subscribe("wavegrasp/gate/decision", w.on_decision, GateDecision)
        bus.subscribe("wavegrasp/sim/outcome", w.on_outcome, GraspOutcome)
        bus.subscribe("wavegrasp/sim/arm_state", w.on_arm_state, ArmState)
        bus.subscribe("wavegrasp/*/stats", w.on_stats, ServiceStats)
        return bus

    def pump(self, seconds: float) -> None:
        deadline = time.monotonic() + seconds
        while time.monotonic() < deadline and not self.run.launcher.interrupted.is_set():
            assert self.bus is not None
            with contextlib.suppress(queue.Empty):
                self.bus.dispatch(self.bus.inbox.get(timeout=0.05))

    def inject(self) -> None:
        launcher = self.run.launcher
        while "player" not in launcher.procs and not launcher.interrupted.is_set():
            time.sleep(0.1)
        self.bus = self.connect()
        try:
            self.pump(3.0)  # the services' first stats: what each subscribes to
            self.bad_input()
            for name in self.kill:
                self.crash(name)
                self.pump(self.pause_s)
            if self.run.tether is not None:
                self.cut_tether("during an approach")
                self.cut_tether("while idle")
        finally:
            self.bus.close()

    def bad_input(self) -> None:
        assert self.bus is not None
        at = self.now_s()
        for service, stats in sorted(self.watch.stats.items()):
            for key in concrete_keys(stats.subscriptions):
                for payload in BAD_INPUTS.values():
                    self.bus.publish_bytes(key, payload, CDR if key in ROS_KEYS else JSON)
                    self.sent[(service, key)] += 1
        deadline = time.monotonic() + 10.0
        while not self.all_counted() and time.monotonic() < deadline:
            self.pump(0.5)  # the services publish their stats every second
        self.counted = {s: dict(st.bad) for s, st in self.watch.stats.items()}
        self.faults.append(Fault("bad input", f"{len(self.sent)} service keys", at,
                                 detail=", ".join(BAD_INPUTS)))

    def all_counted(self) -> bool:
        stats = self.watch.stats
        return all(s in stats and stats[s].bad.get(k, 0) >= n for (s, k), n in self.sent.items())

    def crash(self, name: str) -> None:
        launcher = self.run.launcher
        proc = launcher.procs.get(name)
        if proc is None or proc.poll() is not None:
            return
        fault = Fault("SIGKILL", name, self.now_s())
        down = Down(name, fault, time.monotonic())
        self.faults.append(fault)
        self.down.append(down)
        os.kill(proc.pid, signal.SIGKILL)
        while time.monotonic() < down.until() and not launcher.interrupted.is_set():
            history = launcher.restarts.get(name) or []
            if history and history[-1].back_s is not None:
                fault.back_after_s = round(history[-1].back_s - history[-1].died_s, 2)
                down.back = down.died + fault.back_after_s
                break
            self.pump(0.1)
        self.pump(1.0)

    def cut_tether(self, when: str) -> None:
        """Cut the tether for ``CUT_S`` (during an approach: ``CUT_AFTER_START_S`` after the
        arm begins to execute the next plan, if it does while the run lasts) and judge: the
        arm's side stopped within its watchdog time, it took no path while cut off or stale,
        and every service was heard from again (its stats) after the link returned."""
        tether, w = self.run.tether, self.watch
        assert tether is not None
        plan = ""
        if when == "during an approach":  # the next plan the arm begins to execute
            executed = len(w.executed)
            while len(w.executed) == executed and not self.ended():
                self.pump(0.05)
            self.pump(CUT_AFTER_START_S)
            plan = w.executed[-1] if len(w.executed) > executed else ""
        else:  # no attempt under way: each approach has its outcome
            while len(w.outcomes) < len(w.approaches) and not self.ended():
                self.pump(0.05)
        if self.ended():
            return
        before = {k: w.counter("sim", k) for k in SIM_WATCH}
        fault = Fault("tether cut", when, self.now_s(), detail=f"plan {plan}" if plan else "")
        self.faults.append(fault)
        tether.cut(True)
        self.pump(CUT_S)
        tether.cut(False)
        joined = time.monotonic()
        names = [n for n in self.run.launcher.services if n != "vehicle-router"
                 and n in w.stats]
        while (missing := [n for n in names if w.stats_at.get(n, 0.0) <= joined]) and (
                time.monotonic() - joined < WAIT_BACK_S):
            self.pump(0.1)
        self.pump(1.0)
        delta = {k: w.counter("sim", k) - before[k] for k in SIM_WATCH}
        stop_ms = w.counter("sim", STOP_MS)
        limit_ms = 1e3 * WATCHDOG_S + 100  # the watchdog's time and two of its checks
        fault.back_after_s = round(max(w.stats_at.get(n, 0.0) for n in names) - joined, 2)
        fault.survived = not missing and delta[STOPS] >= 1 and stop_ms <= limit_ms
        fault.lost = (f"arm stopped {stop_ms} ms after the last heartbeat ({delta[STOPS]} "
                      f"stop); paths refused: {delta[REFUSED_CUT]} without heartbeat, "
                      f"{delta[REFUSED_STALE]} stale; "
                      + (f"not heard from again: {', '.join(missing)}" if missing else
                         "every service heard from again"))

    def ended(self) -> bool:
        launcher = self.run.launcher
        return launcher.interrupted.is_set() or any(
            launcher.procs[n].poll() is not None for n in ("player", "sim")
            if n in launcher.procs)

    def settle(self, summary: dict) -> None:
        """Judge each fault once the run is over."""
        for fault in self.faults:
            if fault.kind == "bad input":
                missed = [f"{s} <- {k}" for (s, k), n in self.sent.items()
                          if self.counted.get(s, {}).get(k, 0) < n]
                fault.survived = not missed and summary["ended"] == "finished"
                fault.lost = f"{sum(self.sent.values())} sent, " + (
                    "all counted as bad" if not missed else f"not counted: {', '.join(missed)}")
        for down in self.down:
            name, fault = down.name, down.fault
            fault.survived = (fault.back_after_s is not None
                              and fault.back_after_s <= BACK_WITHIN_S
                              and summary["ended"] == "finished")
            if down.back is None:
                fault.detail = "not back when the run ended"
            frames = self.watch.frames_between(down.died, down.until() + 1.0)
            acked = self.watch.acks.get("perception" if name == "router" else name, set())
            missing = [seq for seq in frames if seq not in acked]
            fault.lost = f"{len(missing)} of {len(frames)} frames not acknowledged"
            if name == "player":
                fault.lost = f"{summary['player'].get('frames', 0)} frames played in all"
            if name == "recorder":
                fault.lost_s, text = recorded_loss(self.run.out, self.watch.acks["recorder"],
                                                   summary["player"].get("frames", 0))
                fault.lost += f"; {text}"
        cuts = [f for f in self.faults if f.kind == "tether cut"]
        if cuts:
            outcomes = summary.get("outcomes") or []
            grasped = bool(outcomes) and bool(outcomes[-1].get("success"))
            self.faults.append(Fault(
                "grasp after the cuts", "sim", 0.0, survived=grasped and len(cuts) == 2,
                lost=f"{len(cuts)} cuts; attempts: " + ", ".join(
                    "success" if o.get("success") else str(o.get("failure") or "aborted")
                    for o in outcomes) if outcomes else "no attempt"))
        approved = [t for t in self.watch.gos for down in self.down
                    if down.name in ("perception", "predictor", "planner", "router")
                    and down.died + 0.1 < t < (down.back or math.inf)]
        self.faults.append(Fault(
            "gate while upstream down", "gate", 0.0, survived=not approved,
            lost=f"{len(approved)} plans approved while an upstream service was down"))


def recorded_loss(out: Path, acked: set[int], played: int) -> tuple[float, str]:
    """What the run's files miss of the camera frames: those the recorder had acknowledged
    (written, but lost when it was killed before its next flush) and the others (not recorded
    while it was down), in frames and seconds of the recording: the seconds of written data
    lost, and the text."""
    seqs: set[int] = set()
    stamps: list[int] = []
    for path in sorted(out.glob("run*.mcap")):
        with contextlib.suppress(RecordingError):  # a killed recorder's file ends early
            for _schema, _channel, message in read_mcap(path, topics=["/trisect/points"]):
                seqs.add(message.sequence)
                stamps.append(message.log_time)
    interval_s = (max(stamps) - min(stamps)) / 1e9 / max(len(stamps) - 1, 1) if stamps else 0.0
    lost = len(acked - seqs)
    down = played - len(seqs) - lost
    return lost * interval_s, (f"files lack {lost} acknowledged frames "
                               f"({lost * interval_s:.1f} s) and {down} more not recorded "
                               f"({down * interval_s:.1f} s: while it, or the router, was "
                               "down)")


def concrete_keys(subscriptions: list[str]) -> list[str]:
    """The keys to send to: wildcard subscriptions (the recorder's ``**``) are left out, the
    other services' keys reach it anyway."""
    return sorted({k for k in subscriptions if "*" not in k})


def bad_files(out: Path) -> list[Fault]:
    """The player on files that are no recording: each must fail with one clear line."""
    faults = []
    for name, content in [("random bytes", bytes(range(256)) * 16),
                          ("a text file", b"frame,x,y,z\n0,1,2,3\n"),
                          ("MCAP header only", b"\x89MCAP0\r\n")]:
        path = out / f"bad-{name.replace(' ', '-')}.mcap"
        path.write_bytes(content)
        result = subprocess.run([sys.executable, "-m", "wavegrasp", "player", str(path)],
                                capture_output=True, text=True, timeout=60,
                                env={**os.environ, "ZENOH_CONNECT": "tcp/127.0.0.1:9"})
        lines = result.stderr.strip().splitlines()
        clear = (result.returncode != 0 and bool(lines) and str(path) in lines[-1]
                 and "Traceback" not in result.stderr)
        faults.append(Fault("bad file", name, 0.0, survived=clear,
                            detail=lines[-1] if lines else f"exit {result.returncode}"))
    return faults


def format_report(faults: list[Fault]) -> str:
    rows = [f"{'fault':26s} {'target':18s} {'at s':>6s} {'back s':>7s}  survived  lost"]
    for f in faults:
        back = f"{f.back_after_s:.2f}" if f.back_after_s is not None else "-"
        rows.append(f"{f.kind:26s} {f.target:18s} {f.at_s:6.1f} {back:>7s}  "
                    f"{'yes' if f.survived else 'NO':8s}  {f.lost or f.detail}")
    n_ok = sum(f.survived for f in faults)
    rows.append(f"{n_ok} of {len(faults)} faults survived")
    return "\n".join(rows)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="wavegrasp faults", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("recording", nargs="?", type=Path,
                   help="default: a 40 s recording (wave 1, buoy, seed 0) from the cache")
    p.add_argument("--out", type=Path, help="run folder (default: runs/faults-<date-time>)")
    p.add_argument("--kill", help="services to kill, in order (default "
                   f"{','.join(KILL_ORDER)}; with --tether none)")
    p.add_argument("--tether", type=float, metavar="MBIT",
                   help="run as `wavegrasp up --tether MBIT` and cut the tether for 2 s, "
                   "once while idle and once during an approach")
    p.add_argument("--pause-s", type=float, default=2.0,
                   help="seconds between a service's return and the next kill")
    a = p.parse_args(argv)
    recording = a.recording or cached_recording(wave=1, object="buoy", seconds=40.0, seed=0)
    out = a.out or Path("runs") / time.strftime("faults-%Y%m%d-%H%M%S")
    try:
        tether = ["--tether", str(a.tether)] if a.tether is not None else []
        run = up.prepare(up.parse_args([str(recording), "--pace", "realtime",
                                        "--out", str(out), *tether]))
    except ValueError as exc:
        print(f"wavegrasp faults: {exc}", file=sys.stderr)
        return 2
    kill_list = a.kill if a.kill is not None else "" if a.tether else ",".join(KILL_ORDER)
    kill = [k for k in kill_list.split(",") if k]
    unknown = [k for k in kill if k not in run.launcher.services]
    if unknown:
        print(f"wavegrasp faults: --kill: no service {', '.join(unknown)}", file=sys.stderr)
        return 2
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: run.launcher.interrupted.set())
    injector = Injector(run, kill, a.pause_s)
    thread = threading.Thread(target=injector.inject, name="faults", daemon=True)
    thread.start()
    why = up.execute(run)
    thread.join(timeout=5.0)
    summary = up.summarize(run, why)
    injector.settle(summary)
    faults = injector.faults + bad_files(run.out)
    report = format_report(faults)
    print(report)
    (run.out / "faults.json").write_text(json.dumps(
        {"recording": str(recording), "faults": [asdict(f) for f in faults],
         "summary": "summary.json"}, indent=2) + "\n")
    return 0 if all(f.survived for f in faults) else 1


if __name__ == "__main__":
    raise SystemExit(main())

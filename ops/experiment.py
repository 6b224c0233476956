"""``wavegrasp eval``: the paper's experiment over the full pipeline.

For every predictor × sea × wave condition × object, one lockstep ``wavegrasp up`` (every
service a process, over zenoh) runs ``--trials`` trials one after the other on a long wave-tank
recording: each trial starts where the previous one ended, with the arm back at standby, and
ends at a success or after ``--attempts`` attempts (or when no plan is approved for 5 s).
Lockstep makes each run repeat exactly; ``--seed`` picks the recordings. ``--seas``: the
paper's regular waves and/or JONSWAP seas of the same significant height and peak period. Each run's
``run.mcap`` holds everything but the camera clouds, which are in the cached recording.
``--jobs`` runs go side by side, or with ``--cluster ray://HOST:PORT`` each on whichever node
of a Ray cluster has a CPU free (:mod:`wavegrasp.ops.cluster`). Writes ``report.json``,
``report.md`` and PNG plots to ``--out``.
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import sys
import threading
import time
from collections import Counter
from collections.abc import Iterator
from concurrent.futures import ProcessPoolExecutor, ThreadPoolExecutor, as_completed
from contextlib import contextmanager, nullcontext
from dataclasses import asdict, dataclass, field
from pathlib import Path

from tqdm import tqdm

from wavegrasp.ops import cluster
from wavegrasp.ops.launcher import up
from wavegrasp.ops.sample import cached_recording
from wavegrasp.predictor import DEFAULT_MODEL, MODELS
from wavegrasp.recorder.main import OBJECT_POINTS_KEY, POINTS_KEY
from wavegrasp.schemas import KEY_TYPES, stats_key
from wavegrasp.wavetank.body import OBJECTS
from wavegrasp.wavetank.suite import SEAS
from wavegrasp.wavetank.waves import TABLE_I

#: Recording seconds before the first trial (the predictor warms up) and per trial.
WARMUP_S = 15.0
PER_TRIAL_S = 6.0
#: A trial with no plan approved this long (recording seconds) ends as a failure.
TRIAL_TIMEOUT_S = 5.0


@dataclass(kw_only=True)
class Trials:
    """What one run's trials came to: per trial, whether it succeeded and on which attempt
    (0: never), every attempt's failure kind, the trials the recording ended first, the run's
    seconds and exit code."""

    trials: int
    success_attempt: list[int] = field(default_factory=list)
    failures: dict[str, int] = field(default_factory=dict)
    unfinished: int = 0
    seconds: float = 0.0
    exit_code: int = 0
    #: Per attempt, recording seconds from its approval to its grasp time.
    approval_to_grasp_s: list[float] = field(default_factory=list)
    #: Per service, the CPU seconds its process used (its last stats; a forked
    #: service's from its fork, not the fork server's loading of the libraries).
    cpu_s: dict[str, float] = field(default_factory=dict)
    #: The gate's figures (approvals, refusals, latency, error at approval: summary.json's
    #: ``gate``), bad messages and service restarts in the run.
    gate: dict = field(default_factory=dict)
    bad_messages: int = 0
    restarts: int = 0
    #: The run's folder, relative to the experiment's.
    run: str = ""

    def rate(self, within: int) -> float:
        """Share of the trials that succeeded within ``within`` attempts."""
        return sum(0 < a <= within for a in self.success_attempt) / max(self.trials, 1)


@dataclass
class RunResult(Trials):
    """One predictor on one of the paper's configurations, in a regular or JONSWAP sea."""

    predictor: str
    wave: int
    object: str
    sea: str = "regular"
    execution: str = "closed"

    @property
    def label(self) -> str:
        """The report's column: the predictor, and its execution where not the default."""
        return self.predictor if self.execution == "closed" else f"{self.predictor} open"

    @property
    def config(self) -> tuple[str, int, str]:
        """The recording's configuration: sea, wave, object."""
        return self.sea, self.wave, self.object


def trial_results(outcomes: list[dict], trials: int, attempts: int
                  ) -> tuple[list[int], dict[str, int], int]:
    """From the sim's outcomes: per trial the succeeding attempt (0: none), the failure
    counts, and how many trials the recording did not reach the end of."""
    success = [0] * trials
    ended = [False] * trials
    failures: dict[str, int] = {}
    for o in outcomes:
        k = o["trial"]
        if k >= trials:
            continue
        if o["success"]:
            success[k], ended[k] = o["attempt"], True
            continue
        kind = "no plan approved" if o["evidence"].get("no_attempt") else (
            "aborted" if o.get("aborted") else o["failure"])
        failures[kind] = failures.get(kind, 0) + 1
        ended[k] = ended[k] or o["evidence"].get("no_attempt", False) or o["attempt"] >= attempts
    return success, failures, sum(not e for e in ended)


def service_cpu(summary: dict) -> dict[str, float]:
    """Per service, the CPU seconds in its last stats in a run's summary.json."""
    return {name: round(float(stats.get("cpu_s", 0.0)), 2)
            for name, stats in summary.get("services", {}).items()}


def approval_times(outcomes: list[dict]) -> list[float]:
    """Each attempt's seconds from its approval to its grasp time (its outcome's evidence)."""
    return [float(o["evidence"]["approval_to_grasp_s"]) for o in outcomes
            if "approval_to_grasp_s" in o["evidence"]]


#: What an experiment run records: every message of the contract, the counters, the object's
#: points and the camera's mount; not the frame acknowledgements (lockstep's bookkeeping, six a
#: frame) nor the clouds and the 100 Hz ground truth, which the cached recording holds (144
#: copies of the clouds would be 64 GB). The clouds are still subscribed, not written: the
#: recorder acknowledges frames on them.
EXPERIMENT_RECORD_KEYS = [*KEY_TYPES, stats_key("*"), OBJECT_POINTS_KEY, "tf_static", POINTS_KEY]


class Cores:
    """The cores this process may use, handed to the runs side by side, the least busy first.

    A lockstep run is a chain (each frame waits on each of its processes in turn) that keeps
    about one core busy. With its processes on a core of their own they hand each frame on
    at once, not after the other run's are switched out (``--no-pin``: anywhere): measured
    in the README's experiment section.
    """

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._runs = Counter({core: 0 for core in sorted(os.sched_getaffinity(0))})

    @contextmanager
    def take(self) -> Iterator[int]:
        """A core for one run while the ``with`` block lasts."""
        with self._lock:
            core = min(self._runs, key=lambda c: (self._runs[c], c))
            self._runs[core] += 1
        try:
            yield core
        finally:
            with self._lock:
                self._runs[core] -= 1


CORES = Cores()


def run_recording(recording: Path, run_dir: Path, predictor: str, trials: int,
                  attempts: int, execution: str = "closed", pin: bool = True
                  ) -> tuple[dict, float, int]:
    """One lockstep ``wavegrasp up`` of ``trials`` trials on ``recording`` into ``run_dir``,
    its processes on one core (:class:`Cores`) if ``pin``: its summary.json, wall seconds and
    exit code."""
    with CORES.take() if pin else nullcontext(None) as core:
        return _run_recording(recording, run_dir, predictor, trials, attempts, execution, core)


def _run_recording(recording: Path, run_dir: Path, predictor: str, trials: int,
                   attempts: int, execution: str, core: int | None) -> tuple[dict, float, int]:
    if STOP.is_set():
        raise Interrupted
    cpus = "" if core is None else str(core)
    env = {**os.environ, "WAVEGRASP_TRIALS": str(trials), "WAVEGRASP_ATTEMPTS": str(attempts),
           "WAVEGRASP_EXECUTION": execution,
           "WAVEGRASP_STOP_AFTER_TRIALS": "true", "WAVEGRASP_TRIAL_TIMEOUT_S": str(TRIAL_TIMEOUT_S),
           "WAVEGRASP_RECORD_KEYS": ",".join(EXPERIMENT_RECORD_KEYS),
           "WAVEGRASP_RECORD_EXCLUDE": "trisect/points",
           # In lockstep every service is on the path a frame waits for: none yields, all
           # share the run's core (none is real-time either, as in every lockstep run); and
           # run.mcap holds what a run.rrd would show (`wavegrasp up` makes one).
           "WAVEGRASP_BACKGROUND_NICE": "0", "WAVEGRASP_HOT_CPUS": cpus,
           "WAVEGRASP_BACKGROUND_CPUS": cpus, "WAVEGRASP_RRD": "false"}
    started = time.monotonic()
    run_dir.mkdir(parents=True, exist_ok=True)
    # `wavegrasp up` in this process: every run's services fork from one fork server, which
    # loaded their libraries once (as a command of its own, each run loaded them again).
    with (run_dir / "up.log").open("w") as log:
        code = up([str(recording), "--pace", "lockstep", "--predictor", predictor,
                   "--out", str(run_dir)], environ=env, log=log, interrupted=STOP)
    if code == 130:
        raise Interrupted
    summary = json.loads((run_dir / "summary.json").read_text())
    return summary, round(time.monotonic() - started, 1), code


class Interrupted(Exception):
    """The experiment was asked to stop (Ctrl-C or SIGTERM): its runs stop their services."""


#: Set on Ctrl-C or SIGTERM (:func:`stoppable`): the runs under way stop, no other starts.
STOP = threading.Event()


@contextmanager
def stoppable() -> Iterator[None]:
    """While the ``with`` block lasts, Ctrl-C and SIGTERM set :data:`STOP`."""
    signals = (signal.SIGINT, signal.SIGTERM)
    before = [signal.signal(sig, lambda *_: STOP.set()) for sig in signals]
    try:
        yield
    finally:
        for sig, handler in zip(signals, before, strict=True):
            signal.signal(sig, handler)
        STOP.clear()


def run_one(predictor: str, execution: str, sea: str, wave: int, obj: str, trials: int,
            attempts: int, seed: int, out: Path, pin: bool = True) -> RunResult:
    recording = _recording((sea, wave, obj, seed, WARMUP_S + trials * PER_TRIAL_S))
    kind = "" if sea == "regular" else f"{sea}-"
    loop = "" if execution == "closed" else f"-{execution}"
    run_dir = out / "runs" / f"{predictor}{loop}-{kind}wave{wave}-{obj}"
    summary, seconds, code = run_recording(recording, run_dir, predictor, trials, attempts,
                                           execution, pin)
    success, failures, unfinished = trial_results(summary.get("outcomes", []), trials, attempts)
    return RunResult(predictor, wave, obj, sea, execution, trials=trials,
                     success_attempt=success, failures=failures, unfinished=unfinished,
                     seconds=seconds, exit_code=code,
                     approval_to_grasp_s=approval_times(summary.get("outcomes", [])),
                     cpu_s=service_cpu(summary), gate=summary.get("gate", {}),
                     bad_messages=sum(sum(per_key.values()) for per_key
                                      in summary.get("bad_messages", {}).values()),
                     restarts=sum(map(len, summary.get("restarts", {}).values())),
                     run=str(run_dir.relative_to(out)))


def main(argv: list[str] | None = None) -> int:
    args = sys.argv[1:] if argv is None else argv
    if any(a == "--suite" or a.startswith("--suite=") for a in args):
        from wavegrasp.ops.suite import main as suite_main

        return suite_main(args)
    p = argparse.ArgumentParser(prog="wavegrasp eval", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter,
                                epilog="wavegrasp eval --suite random --help: the random "
                                "scenario suite")
    p.add_argument("--out", type=Path, required=True)
    p.add_argument("--trials", type=int, default=20)
    p.add_argument("--attempts", type=int, default=3)
    p.add_argument("--predictors", default=f"harmonic,linear,{DEFAULT_MODEL}")
    p.add_argument("--seas", default="regular", help=f"of {', '.join(SEAS)}")
    p.add_argument("--executions", default="closed", help="closed (updates on every "
                   "prediction, the gate may abort) and/or open (the paper's)")
    p.add_argument("--waves", default=",".join(str(w) for w in TABLE_I))
    p.add_argument("--objects", default=",".join(OBJECTS))
    p.add_argument("--seed", type=int, default=0)
    # As many runs as cores: a lockstep run keeps about 1.2 cores busy (its frame waits on
    # each process in turn), and one run more than cores (eight processes each) lost more to
    # contention than it filled: on 2 cores 16.8 min against 13.4 for the whole experiment.
    p.add_argument("--jobs", type=int, default=os.cpu_count() or 1)
    p.add_argument("--no-pin", dest="pin", action="store_false",
                   help="let each run's processes use any core (default: each run on a core "
                   "of its own, the least busy)")
    p.add_argument("--cluster", metavar="ray://HOST:PORT",
                   help="run each run as a task on this Ray cluster (the cluster extra: pip "
                   "install 'wavegrasp[cluster]'), its recording generated on its node; "
                   "--jobs and --no-pin then do not apply")
    a = p.parse_args(args)
    predictors = a.predictors.split(",")
    seas = a.seas.split(",")
    executions = a.executions.split(",")
    waves = [int(w) for w in a.waves.split(",")]
    objects = a.objects.split(",")
    bad = [x for x in predictors if x not in MODELS] + [str(w) for w in waves
                                                         if w not in TABLE_I]
    bad += [o for o in objects if o not in OBJECTS] + [x for x in seas if x not in SEAS]
    bad += [x for x in executions if x not in ("closed", "open")]
    if bad:
        p.error(f"unknown {', '.join(bad)}: predictors {', '.join(MODELS)}; seas "
                f"{', '.join(SEAS)}; executions closed, open; waves "
                f"{', '.join(map(str, TABLE_I))}; objects {', '.join(OBJECTS)}")
    if a.cluster:
        try:
            cluster.check_address(a.cluster)
        except ValueError as exc:
            p.error(str(exc))
    a.out.mkdir(parents=True, exist_ok=True)
    started = time.monotonic()
    configs = [(sea, w, o) for sea in seas for w in waves for o in objects]
    jobs = [(pred, x, *c) for pred in predictors for x in executions for c in configs]
    results: list[RunResult] = []  # as they finish
    try:
        if a.cluster:
            run_cluster(a, jobs, results)
        else:
            run_here(a, configs, jobs, results)
    except Interrupted:
        print(f"wavegrasp eval: interrupted after {len(results)} of {len(jobs)} runs",
              file=sys.stderr)
        return 130
    except cluster.ClusterError as exc:
        print(f"wavegrasp eval: {exc}", file=sys.stderr)
        return 2
    order = {job: i for i, job in enumerate(jobs)}
    results.sort(key=lambda r: order[(r.predictor, r.execution, *r.config)])
    from wavegrasp.ops.report import end_table, write_report

    elapsed = time.monotonic() - started
    write_report(a.out, results, vars(a) | {"out": str(a.out), "elapsed_s": round(elapsed, 1)})
    print(end_table(a.out, results))
    return 1 if any(r.exit_code for r in results) else 0


def run_here(a: argparse.Namespace, configs: list[tuple], jobs: list[tuple],
             results: list[RunResult]) -> None:
    """The runs on this machine into ``results``, ``--jobs`` at a time, the recordings made
    first (cached; one per configuration, shared by the predictors)."""
    seconds = WARMUP_S + a.trials * PER_TRIAL_S
    with ProcessPoolExecutor(min(a.jobs, os.cpu_count() or 1)) as pool:  # CPU-bound
        list(tqdm(pool.map(_recording, [(*c, a.seed, seconds) for c in configs]),
                  total=len(configs), desc="recordings", unit="rec"))
    with stoppable(), ThreadPoolExecutor(a.jobs) as pool:
        futures = [pool.submit(run_one, *job, a.trials, a.attempts, a.seed, a.out, a.pin)
                   for job in jobs]
        for f in tqdm(as_completed(futures), total=len(futures), desc="runs", unit="run"):
            results.append(f.result())


def run_cluster(a: argparse.Namespace, jobs: list[tuple], results: list[RunResult]) -> None:
    """The runs into ``results`` as tasks on the Ray cluster ``a.cluster``, each making its
    own recording on its node, none pinned (Ray gives each task its CPU)."""
    out = a.out.resolve()  # a task does not start in our folder
    tasks = [(*job, a.trials, a.attempts, a.seed, out, False) for job in jobs]
    with stoppable():
        cluster.run_on_cluster(a.cluster, run_one, tasks, results, STOP, Interrupted)


def _recording(config: tuple[str, int, str, int, float]) -> Path:
    sea, wave, obj, seed, seconds = config
    return cached_recording(wave=wave, object=obj, seed=seed, seconds=seconds,
                            irregular=sea == "jonswap")


def as_json(results: list[RunResult]) -> list[dict]:
    return [asdict(r) for r in results]


if __name__ == "__main__":
    raise SystemExit(main())

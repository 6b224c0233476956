"""``wavegrasp eval``: trials are counted from the sim's outcomes; a small experiment end to end."""

from __future__ import annotations

import json
import os
import signal
import subprocess
from pathlib import Path

import psutil

from wavegrasp.ops.experiment import Cores, RunResult, trial_results

from conftest import spawn, wait_until, wavegrasp_cmd


def outcome(trial: int, attempt: int, success: bool, failure: str | None = None,
            **evidence) -> dict:
    return {"trial": trial, "attempt": attempt, "success": success, "failure": failure,
            "evidence": evidence}


def test_trials_are_counted_from_the_outcomes() -> None:
    outcomes = [
        outcome(0, 1, True),                                   # first attempt
        outcome(1, 1, False, "timing"), outcome(1, 2, True),   # second attempt
        outcome(2, 1, False, "collision"), outcome(2, 2, False, "prediction"),
        outcome(2, 3, False, "prediction"),                    # three failures: trial over
        outcome(3, 0, False, "other", no_attempt=True),        # nothing approved in time
        outcome(4, 1, False, "timing"),                        # the recording ended
    ]
    success, failures, unfinished = trial_results(outcomes, trials=5, attempts=3)
    assert success == [1, 2, 0, 0, 0]
    assert failures == {"timing": 2, "collision": 1, "prediction": 2, "no plan approved": 1}
    assert unfinished == 1
    run = RunResult("blend", 2, "can_half", trials=5, success_attempt=success,
                    failures=failures, unfinished=unfinished)
    assert run.rate(1) == 0.2 and run.rate(3) == 0.4


def test_runs_side_by_side_each_get_the_least_busy_core() -> None:
    cores = Cores()
    mine = sorted(os.sched_getaffinity(0))
    with cores.take() as first:
        assert first == mine[0]
        with cores.take() as second:  # another core while there is one; else shared
            assert second == (mine[1] if len(mine) > 1 else mine[0])
        with cores.take() as third:  # the one given back is the least busy again
            assert third == second
    with cores.take() as again:
        assert again == mine[0]


def test_the_report_gives_each_sea_its_own_rows(tmp_path: Path) -> None:
    from wavegrasp.ops.report import write_report

    runs = [RunResult("blend", 2, "can_half", sea, trials=2, success_attempt=attempts,
                      approval_to_grasp_s=times, failures=failures)
            for sea, attempts, times, failures in (
                ("regular", [1, 1], [1.0, 1.2], {}),
                ("jonswap", [2, 0], [1.4, 2.0, 3.0, 2.2, 2.6], {"aborted": 1}))]
    write_report(tmp_path, runs, {"trials": 2, "attempts": 3, "seed": 0, "elapsed_s": 60.0})
    md = (tmp_path / "report.md").read_text()
    assert "| regular | 2 | can_half | 100% / 100% |" in md
    assert "| jonswap | 2 | can_half | 0% / 50% |" in md
    assert "**50.0% / 75.0%**" in md  # the mean over both
    assert "| blend | 7 | 1 | 2.00 | 2.76 |" in md  # attempts, aborts, approval to grasp
    assert json.loads((tmp_path / "report.json").read_text())["runs"][1]["sea"] == "jonswap"


def test_the_experiment_ends_with_a_row_per_run_and_where_to_look(tmp_path: Path) -> None:
    from wavegrasp.ops.report import end_table

    gate = {"plans_approved": 3, "updates_approved": 40, "refused": 7, "latency_p50_ms": 41.2,
            "latency_p99_ms": 88.9, "error_at_approval_mm": [2.0, 4.0, 3.0]}
    runs = [RunResult("blend", 2, "can_half", trials=2, success_attempt=[1, 0],
                      failures={"aborted": 1, "timing": 2}, gate=gate, bad_messages=1,
                      restarts=0, run="runs/blend-wave2-can_half"),
            RunResult("linear", 2, "can_half", trials=2, success_attempt=[2, 1],
                      failures={"timing": 1}, run="runs/linear-wave2-can_half")]
    lines = end_table(tmp_path, runs).splitlines()
    assert lines[1].split() == ["runs/blend-wave2-can_half", "1,-", "aborted", "1,", "timing",
                                "2", "3.0", "mm", "3/40/7", "41/89", "1", "0"]
    assert lines[2].split()[1:4] == ["2,1", "timing", "1"]  # no gate figures: dashes
    assert lines[2].split()[4:7] == ["-", "0/0/0", "-"]
    assert lines[3] == "blend: success 50% first attempt, 50% after reattempts, 2 trials"
    assert lines[4] == "linear: success 50% first attempt, 100% after reattempts, 2 trials"
    assert lines[5].startswith(f"see it: the report {tmp_path / 'report.md'}")
    assert f"open {tmp_path}/RUN/run.mcap" in lines[5]


def run_eval(out: Path, *extra: str) -> dict:
    result = subprocess.run(wavegrasp_cmd(
        "eval", "--out", str(out), "--trials", "2", "--waves", "2", "--objects", "can_half",
        "--predictors", "blend", "--jobs", "1", *extra), capture_output=True, text=True,
        timeout=600)
    assert result.returncode == 0, result.stdout[-3000:] + result.stderr[-3000:]
    return json.loads((out / "report.json").read_text())


def test_a_small_experiment_end_to_end_repeats_exactly(tmp_path: Path) -> None:
    out = tmp_path / "eval"
    report = run_eval(out)
    (run,) = report["runs"]
    assert run["predictor"] == "blend" and run["trials"] == 2
    # The report counts exactly what the sim published in the run.
    summary = json.loads((out / "runs" / "blend-wave2-can_half" / "summary.json").read_text())
    assert summary["ended"] == "finished"
    success, _, _ = trial_results(summary["outcomes"], 2, 3)
    assert run["success_attempt"] == success
    assert sum(a > 0 for a in success) >= 1, summary["outcomes"]
    assert (out / "success.png").stat().st_size > 1000
    assert (out / "failures.png").stat().st_size > 1000
    assert "| 2 | can_half |" in (out / "report.md").read_text()
    # Where the run's CPU went, per service, from each one's last stats.
    assert {"perception", "predictor", "planner", "gate", "sim", "recorder"} <= set(run["cpu_s"])
    assert all(cpu > 0 for cpu in run["cpu_s"].values()), run["cpu_s"]
    assert "CPU seconds per service" in (out / "report.md").read_text()
    # The gate's figures, from the run's own summary.json, for the end table.
    assert run["run"] == "runs/blend-wave2-can_half"
    assert run["gate"] == summary["gate"] and run["gate"]["plans_approved"] >= 1
    assert run["gate"]["latency_p50_ms"] <= run["gate"]["latency_p99_ms"]
    again = run_eval(tmp_path / "again")  # lockstep: the same trials, attempt for attempt
    assert again["runs"][0]["success_attempt"] == run["success_attempt"]
    assert again["runs"][0]["failures"] == run["failures"]


#: The outcomes of ``run_eval`` on 6ebd9f1, before closed-loop execution existed
#: (tests/data/open-loop-outcomes.json: plan_id, trial, attempt, success, failure of each).
BEFORE = Path(__file__).with_name("data") / "open-loop-outcomes.json"


def test_open_loop_repeats_the_outcomes_from_before_closed_loop_execution(
        tmp_path: Path) -> None:
    out = tmp_path / "open"
    run_eval(out, "--executions", "open")
    summary = json.loads((out / "runs" / "blend-open-wave2-can_half" / "summary.json"
                          ).read_text())
    fields = ("plan_id", "trial", "attempt", "success", "failure")
    got = [{k: o[k] for k in fields} for o in summary["outcomes"]]
    assert got == json.loads(BEFORE.read_text())
    assert not any(o["aborted"] for o in summary["outcomes"])


def test_ctrl_c_stops_the_runs_under_way_and_leaves_no_service_behind(tmp_path: Path) -> None:
    """The runs are ``wavegrasp up`` in the experiment's own process: Ctrl-C stops their
    services (forked from its fork server, each in a session of its own) and starts no
    other run."""
    evaluation = spawn(wavegrasp_cmd(
        "eval", "--out", str(tmp_path / "eval"), "--trials", "2", "--waves", "2",
        "--objects", "can_half,buoy", "--predictors", "blend", "--jobs", "1"), {},
        stdout=subprocess.PIPE, stderr=subprocess.STDOUT)
    root = psutil.Process(evaluation.pid)

    def services() -> dict[str, psutil.Process]:
        """The experiment's services by title (forked: ``wavegrasp NAME``)."""
        found = {}
        for proc in root.children(recursive=True):
            try:
                title = " ".join(proc.cmdline())
            except psutil.Error:
                continue
            if title.startswith("wavegrasp "):
                found[title] = proc
        return found

    assert wait_until(lambda: any("player" in title for title in services()), timeout=120), (
        "no run started")
    running = list(services().values())
    os.kill(evaluation.pid, signal.SIGINT)
    output = evaluation.communicate(timeout=60)[0].decode()
    assert evaluation.returncode == 130, output[-3000:]
    assert "interrupted after 0 of 2 runs" in output
    assert wait_until(lambda: not any(p.is_running() and p.status() != psutil.STATUS_ZOMBIE
                                      for p in running), timeout=10)
    assert json.loads((tmp_path / "eval" / "runs" / "blend-wave2-can_half" / "summary.json")
                      .read_text())["ended"] == "interrupted"
    assert not (tmp_path / "eval" / "runs" / "blend-wave2-buoy").exists()

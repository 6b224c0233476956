"""Where service processes run: CPU lists, pinning of every thread, the compose file's split."""

from __future__ import annotations

import os
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest
import yaml

from wavegrasp.ops.compose import load_compose
from wavegrasp.ops.launcher import parse_args, prepare
from wavegrasp.perception.main import mesh_worker_setup
from wavegrasp.runtime.placement import parse_cpus, parse_rt_priority

ROOT = Path(__file__).resolve().parents[1]
DECISION_PATH = {"router", "perception", "predictor", "planner", "gate"}


def test_parse_cpus_reads_linux_cpu_lists() -> None:
    assert parse_cpus("") == set()
    assert parse_cpus("0") == {0}
    assert parse_cpus("0-2") == {0, 1, 2}
    assert parse_cpus("0, 2-3,7") == {0, 2, 3, 7}


@pytest.mark.parametrize("text", ["a", "1-", "3-1", "-1", "0,x-2"])
def test_parse_cpus_names_the_bad_part(text: str) -> None:
    with pytest.raises(ValueError, match="is not a CPU number or range"):
        parse_cpus(text)


def test_compose_puts_the_decision_path_on_the_hot_cpus() -> None:
    services = load_compose(ROOT / "docker-compose.yml", {"WAVEGRASP_HOT_CPUS": "2-3",
                                                           "WAVEGRASP_BACKGROUND_CPUS": "4"})
    cpus = {name: svc.environment.get("WAVEGRASP_CPUS") for name, svc in services.items()}
    assert {n for n, c in cpus.items() if c == "2-3"} == DECISION_PATH
    assert {n for n, c in cpus.items() if c == "4"} == {"player", "recorder", "sim"}
    assert services["perception"].environment["WAVEGRASP_WORKER_CPUS"] == "4"
    unset = load_compose(ROOT / "docker-compose.yml", {})
    assert unset["perception"].environment["WAVEGRASP_CPUS"] == ""  # anywhere
    assert unset["sim"].environment["WAVEGRASP_CPUS"] == "1"


def test_compose_runs_the_path_real_time_with_priorities_rising_along_it() -> None:
    services = load_compose(ROOT / "docker-compose.yml", {})
    priority = {name: svc.environment.get("WAVEGRASP_RT_PRIORITY")
                for name, svc in services.items()}
    path = ["player", "perception", "predictor", "planner", "gate", "router"]
    values = [int(priority[name]) for name in path]
    assert values == sorted(set(values)), dict(zip(path, values, strict=True))
    assert {n for n, p in priority.items() if p is not None} == set(path)
    assert all(services[n].environment["WAVEGRASP_REALTIME"] == "on" for n in path)
    off = load_compose(ROOT / "docker-compose.yml", {"WAVEGRASP_REALTIME": "off"})
    assert all(off[n].environment["WAVEGRASP_REALTIME"] == "off" for n in path)
    # Docker lets a container change its scheduling policy only with this capability; the
    # edge stage (profile edge) is on the path where a tether runs, at the camera's priority.
    doc = yaml.safe_load((ROOT / "docker-compose.yml").read_text())
    assert {n for n, s in doc["services"].items() if "SYS_NICE" in s.get("cap_add", [])} == (
        set(path) | {"edge"})
    edge = load_compose(ROOT / "docker-compose.yml", {}, frozenset({"edge"}))["edge"]
    assert edge.environment["WAVEGRASP_RT_PRIORITY"] == priority["player"]


def test_parse_rt_priority() -> None:
    assert parse_rt_priority("") is None
    assert parse_rt_priority("12") == 12
    assert parse_rt_priority("12", "off") is None
    assert parse_rt_priority("12", "On") == 12


@pytest.mark.parametrize(("text", "switch", "named"), [
    ("0", "on", "WAVEGRASP_RT_PRIORITY"), ("100", "on", "WAVEGRASP_RT_PRIORITY"),
    ("high", "on", "WAVEGRASP_RT_PRIORITY"), ("12", "maybe", "WAVEGRASP_REALTIME")])
def test_a_malformed_rt_setting_is_named(text: str, switch: str, named: str) -> None:
    with pytest.raises(ValueError, match=named):
        parse_rt_priority(text, switch)


def thread_cpus(pid: int) -> list[str]:
    """Cpus_allowed_list of every thread of ``pid``."""
    out = []
    for task in Path(f"/proc/{pid}/task").iterdir():
        for line in (task / "status").read_text().splitlines():
            if line.startswith("Cpus_allowed_list:"):
                out.append(line.split(":", 1)[1].strip())
    return out


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def start_router(cpus: str, **env: str) -> subprocess.Popen[str]:
    env = {**os.environ, "WAVEGRASP_CPUS": cpus,
           "ZENOH_LISTEN": f"tcp/127.0.0.1:{free_port()}", **env}
    return subprocess.Popen([sys.executable, "-m", "wavegrasp", "router"], env=env,
                            stderr=subprocess.PIPE, text=True)


def thread_policies(pid: int) -> list[tuple[int, int]]:
    """(policy, priority) of every thread of ``pid``, once its zenoh threads have started."""
    deadline = time.monotonic() + 20
    while len(thread_cpus(pid)) < 3 and time.monotonic() < deadline:
        time.sleep(0.1)
    tids = [int(task.name) for task in Path(f"/proc/{pid}/task").iterdir()]
    return [(os.sched_getscheduler(t), os.sched_getparam(t).sched_priority) for t in tids]


def realtime_allowed() -> bool:
    """Whether a process of ours may switch to SCHED_FIFO (root, CAP_SYS_NICE or an rtprio
    limit); the services then must, and otherwise must say they could not."""
    probe = "import os; os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(1))"
    return subprocess.run([sys.executable, "-c", probe], capture_output=True).returncode == 0


@pytest.mark.skipif(not hasattr(os, "sched_setscheduler"), reason="Linux scheduling policies")
def test_a_real_time_service_runs_every_thread_under_fifo_or_says_it_cannot() -> None:
    proc = start_router("", WAVEGRASP_RT_PRIORITY="7")
    try:
        policies = thread_policies(proc.pid)
    finally:
        proc.terminate()
        _, err = proc.communicate(timeout=10)
    assert len(policies) >= 3
    if realtime_allowed():
        assert set(policies) == {(os.SCHED_FIFO, 7)}
        assert "warning" not in err
    else:
        assert set(policies) == {(os.SCHED_OTHER, 0)}
        assert "WAVEGRASP_RT_PRIORITY=7: real-time scheduling not allowed here" in err


@pytest.mark.skipif(not hasattr(os, "sched_setscheduler"), reason="Linux scheduling policies")
def test_realtime_off_keeps_the_normal_policy() -> None:
    proc = start_router("", WAVEGRASP_RT_PRIORITY="7", WAVEGRASP_REALTIME="off")
    try:
        policies = thread_policies(proc.pid)
    finally:
        proc.terminate()
        proc.communicate(timeout=10)
    assert set(policies) == {(os.SCHED_OTHER, 0)}


@pytest.mark.skipif(not realtime_allowed(), reason="real-time scheduling not allowed here")
def test_the_mesh_worker_of_a_real_time_perception_runs_under_the_normal_policy() -> None:
    code = """if True:
        import multiprocessing as mp, os, threading
        from concurrent.futures import ProcessPoolExecutor
        from wavegrasp.perception.main import start_mesh_worker
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(5))
        def policy():
            tid = threading.get_native_id()
            return os.sched_getscheduler(tid), os.getpriority(os.PRIO_PROCESS, tid)
        with ProcessPoolExecutor(1, mp.get_context("fork"), initializer=start_mesh_worker,
                                 initargs=("",)) as pool:
            print(*pool.submit(policy).result(), *policy())
    """
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         check=True).stdout.split()
    assert [int(v) for v in out] == [os.SCHED_OTHER, 10, os.SCHED_FIFO, 0]


@pytest.mark.skipif(not hasattr(os, "sched_getaffinity"), reason="Linux CPU affinity")
def test_a_pinned_service_runs_every_thread_on_its_cpus() -> None:
    cpu = min(os.sched_getaffinity(0))
    proc = start_router(str(cpu))
    try:
        deadline = time.monotonic() + 20
        while len(thread_cpus(proc.pid)) < 3 and time.monotonic() < deadline:
            time.sleep(0.1)  # the zenoh session's threads have started
        allowed = thread_cpus(proc.pid)
        assert len(allowed) >= 3
        assert set(allowed) == {str(cpu)}
    finally:
        proc.terminate()
        proc.wait(10)


@pytest.mark.skipif(not hasattr(os, "sched_getaffinity"), reason="Linux CPU affinity")
def test_cpus_that_do_not_exist_leave_the_service_unpinned_with_a_warning() -> None:
    proc = start_router("4000-4001")
    try:
        deadline = time.monotonic() + 20
        while len(thread_cpus(proc.pid)) < 3 and time.monotonic() < deadline:
            time.sleep(0.1)
        mine = os.sched_getaffinity(0)
        assert os.sched_getaffinity(proc.pid) == mine
    finally:
        proc.terminate()
        _, err = proc.communicate(timeout=10)
    assert "WAVEGRASP_CPUS=4000-4001 names no CPU this process may use" in err


def test_a_malformed_cpu_list_stops_the_service_and_says_why() -> None:
    proc = start_router("zero")
    _, err = proc.communicate(timeout=30)
    assert proc.returncode == 2
    assert "WAVEGRASP_CPUS: 'zero' is not a CPU number or range" in err


@pytest.mark.skipif(not hasattr(os, "sched_getaffinity"), reason="Linux CPU affinity")
def test_the_mesh_worker_thread_runs_on_its_own_cpus(caplog: pytest.LogCaptureFixture) -> None:
    cpu = max(os.sched_getaffinity(0))
    seen: dict[str, set[int]] = {}

    def work(cpus: str) -> None:
        mesh_worker_setup(cpus)
        seen[cpus] = os.sched_getaffinity(0)  # 0: this thread

    for cpus in (str(cpu), "4000"):
        thread = threading.Thread(target=work, args=(cpus,))
        thread.start()
        thread.join()
    assert seen[str(cpu)] == {cpu}
    assert seen["4000"] == os.sched_getaffinity(0)  # nothing usable: left as it was
    assert "WAVEGRASP_WORKER_CPUS=4000 names no CPU this process may use" in caplog.text
    assert os.sched_getaffinity(0) != {cpu} or len(os.sched_getaffinity(0)) == 1  # ours kept


@pytest.mark.parametrize(("pace", "env", "expected"), [
    ("realtime", {}, "on"), ("fast", {}, "off"), ("lockstep", {}, "off"),
    ("fast", {"WAVEGRASP_REALTIME": "on"}, "on"),
    ("realtime", {"WAVEGRASP_REALTIME": "off"}, "off")])
def test_wavegrasp_up_runs_real_time_only_at_the_recordings_rate(
        pace: str, env: dict[str, str], expected: str, recording: Path, tmp_path: Path,
        monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv("WAVEGRASP_REALTIME", raising=False)
    for name, value in env.items():
        monkeypatch.setenv(name, value)
    run = prepare(parse_args([str(recording), "--pace", pace, "--out", str(tmp_path / "run")]))
    path = [svc for svc in run.launcher.services.values()
            if "WAVEGRASP_RT_PRIORITY" in svc.environment]
    assert len(path) == 6
    assert {svc.environment["WAVEGRASP_REALTIME"] for svc in path} == {expected}


def test_the_mesh_worker_process_ends_with_a_killed_perception(router) -> None:
    """Meshing runs in a process of its own (not a thread: it held the interpreter lock for
    tens of milliseconds); killed, perception leaves no worker behind."""
    import psutil

    proc = subprocess.Popen([sys.executable, "-m", "wavegrasp", "perception"],
                            env={**os.environ, **router.env}, stderr=subprocess.DEVNULL)
    try:
        deadline = time.monotonic() + 30
        while not psutil.Process(proc.pid).children() and time.monotonic() < deadline:
            time.sleep(0.1)
        workers = psutil.Process(proc.pid).children()
        assert len(workers) == 1
        proc.kill()
        proc.wait(10)
        _, alive = psutil.wait_procs(workers, timeout=10)
        assert not alive
    finally:
        if proc.poll() is None:
            proc.kill()

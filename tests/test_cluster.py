"""``wavegrasp eval --cluster``: a Ray cluster started here runs a small experiment whose report
equals the local run's, timings aside (lockstep runs repeat exactly wherever they run)."""

from __future__ import annotations

import json
import os
import socket
import subprocess
import sys
from pathlib import Path

EVAL = [sys.executable, "-m", "wavegrasp", "eval", "--predictors", "linear,blend", "--waves",
        "2", "--objects", "buoy", "--trials", "2", "--attempts", "1"]
ENV = {**os.environ, "RAY_USAGE_STATS_ENABLED": "0"}


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def without_timings(report: dict) -> dict:
    for run in report["runs"]:
        del run["seconds"], run["cpu_s"]
        del run["gate"]["latency_p50_ms"], run["gate"]["latency_p99_ms"]
    del report["settings"]  # the folder, --cluster, the elapsed time
    return report


def client_server_logs() -> str:
    """The tails of the head's client-server logs, where Ray says why a client's server did
    not start."""
    logs = sorted(Path("/tmp/ray/session_latest/logs").glob("ray_client_server*"))
    return "".join(f"\n--- {p.name}\n{p.read_text(errors='replace')[-1500:]}" for p in logs)


def test_a_ray_cluster_runs_the_experiment_as_this_machine_does(tmp_path: Path) -> None:
    ray = str(Path(sys.executable).with_name("ray"))
    client_port = free_port()
    subprocess.run([ray, "start", "--head", "--node-ip-address=127.0.0.1",
                    f"--port={free_port()}", f"--ray-client-server-port={client_port}",
                    "--num-cpus=2", "--include-dashboard=false", "--disable-usage-stats"],
                   check=True, env=ENV, capture_output=True)
    try:
        local = subprocess.run([*EVAL, "--out", str(tmp_path / "local")], env=ENV,
                               capture_output=True, text=True, timeout=600)
        assert local.returncode == 0, local.stderr[-2000:]
        remote = subprocess.run([*EVAL, "--out", str(tmp_path / "cluster"), "--cluster",
                                 f"ray://127.0.0.1:{client_port}"], env=ENV,
                                capture_output=True, text=True, timeout=600)
        assert remote.returncode == 0, remote.stderr[-2000:] + client_server_logs()
    finally:
        subprocess.run([ray, "stop", "--force"], env=ENV, capture_output=True)
    here, there = (json.loads((tmp_path / d / "report.json").read_text())
                   for d in ("local", "cluster"))
    assert there["settings"]["cluster"] == f"ray://127.0.0.1:{client_port}"
    assert len(there["runs"]) == 2 and all(r["trials"] == 2 for r in there["runs"])
    assert without_timings(there) == without_timings(here)
    # Each task wrote its run where a local run does (one machine: the same storage).
    assert sorted(p.name for p in (tmp_path / "cluster" / "runs").iterdir()) == sorted(
        p.name for p in (tmp_path / "local" / "runs").iterdir())


def test_a_cluster_address_that_is_none_gets_one_line_and_exit_2(tmp_path: Path) -> None:
    bad = subprocess.run([*EVAL, "--out", str(tmp_path), "--cluster", "localhost:10001"],
                         env=ENV, capture_output=True, text=True)
    assert bad.returncode == 2
    assert "--cluster 'localhost:10001': expected ray://HOST:PORT" in bad.stderr

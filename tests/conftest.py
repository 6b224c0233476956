"""Shared fixtures: a real zenoh router process, a test-side bus, generated recordings."""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import pytest
from mcap.reader import make_reader

from wavegrasp.ops.launcher import free_port
from wavegrasp.recording_io.own_messages import read_own
from wavegrasp.recording_io.reader import open_recording
from wavegrasp.runtime.bus import Bus
from wavegrasp.runtime.settings import Settings
from wavegrasp.wavetank.record import RecordConfig, generate

ROOT = Path(__file__).resolve().parent.parent

# test_fuzz.py's helpers assert too: have pytest explain their failures as in a test module
pytest.register_assert_rewrite("fuzz_cases", "fuzz_harness", "fuzz_pipeline",
                               "fuzz_sim_recorder_player")


def wavegrasp_cmd(*args: str) -> list[str]:
    return [sys.executable, "-m", "wavegrasp", *args]


def spawn(args: list[str], env: dict[str, str], **kw) -> subprocess.Popen:
    """Start a wavegrasp process in its own process group (so a kill reaches all of it)."""
    return subprocess.Popen(args, env={**os.environ, **env, "PYTHONUNBUFFERED": "1"},
                            start_new_session=True, **kw)


def stop(proc: subprocess.Popen, sig: int = signal.SIGTERM, timeout: float = 10.0) -> int:
    if proc.poll() is None:
        os.killpg(proc.pid, sig)
        try:
            proc.wait(timeout)
        except subprocess.TimeoutExpired:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
    return proc.returncode


class Router:
    def __init__(self) -> None:
        self.port = free_port()
        self.endpoint = f"tcp/127.0.0.1:{self.port}"
        self.env = {"ZENOH_CONNECT": self.endpoint}
        self.proc = spawn(wavegrasp_cmd("router", "--listen", self.endpoint), {})
        deadline = time.monotonic() + 15
        while time.monotonic() < deadline:
            with socket.socket() as s:
                if s.connect_ex(("127.0.0.1", self.port)) == 0:
                    return
            time.sleep(0.05)
        raise RuntimeError("router did not start listening")

    def bus(self, name: str = "test", **env: str) -> Bus:
        return Bus(Settings.from_env(name, env={**self.env, **env}))


@pytest.fixture
def router() -> Iterator[Router]:
    r = Router()
    yield r
    stop(r.proc)


def make_recording(path: Path, seconds: float, seed: int = 0, wave: int = 1,
                   object: str = "buoy", preroll_s: float = 5.0) -> Path:
    """A wave-tank recording per the recording contract (10 camera frames a second)."""
    generate(RecordConfig(wave=wave, object=object, seconds=seconds, seed=seed,
                          preroll_s=preroll_s), path)
    return path


@pytest.fixture(scope="session")
def recording(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A short recording that follows the recording contract (5 s, 50 camera frames)."""
    return make_recording(tmp_path_factory.mktemp("rec") / "tank.mcap", seconds=5.0, seed=7)


def recorded(run_mcap: Path) -> tuple[dict[str, list[bytes]], dict[str, tuple[str, str]]]:
    """Payloads per topic, and (schema name, schema encoding) per topic, of a run file."""
    payloads: dict[str, list[bytes]] = {}
    schemas: dict[str, tuple[str, str]] = {}
    with run_mcap.open("rb") as f:
        for schema, channel, message in make_reader(f).iter_messages(log_time_order=False):
            payloads.setdefault(channel.topic, []).append(message.data)
            assert schema is not None and schema.data, f"{channel.topic} has no schema"
            schemas[channel.topic] = (schema.name, schema.encoding)
    return payloads, schemas


def own_messages(run_mcap: Path, key: str) -> list[dict]:
    """Our messages on ``key`` in a run file, as dicts (ROS 2 channels, or JSON ones)."""
    return [msg.model_dump() for _, msg, _ in read_own(run_mcap, [key])]


def source_frames(recording: Path) -> list[bytes]:
    return [m.cdr for m in open_recording(recording).messages() if m.topic == "/trisect/points"]


def wait_until(predicate, timeout: float = 10.0, period: float = 0.05) -> bool:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if predicate():
            return True
        time.sleep(period)
    return predicate()

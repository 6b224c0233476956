"""The launcher as users run it: bad input on every key while it runs, and Ctrl-C."""

from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import psutil
import pytest
import zenoh

from wavegrasp.ops.compose import ComposeService
from wavegrasp.ops.faults import BAD_INPUTS
from wavegrasp.ops.launcher import Launcher
from wavegrasp.runtime.bus import CDR, JSON, Bus
from wavegrasp.runtime.settings import Settings
from wavegrasp.schemas import KEY_TYPES, ROS_KEYS, ServiceStats, ack_key, stats_key

from conftest import free_port, make_recording, spawn, wait_until, wavegrasp_cmd

GARBAGE = list(BAD_INPUTS.values())  # what `wavegrasp faults` sends


@pytest.fixture(scope="module")
def long_recording(tmp_path_factory: pytest.TempPathFactory) -> Path:
    path = tmp_path_factory.mktemp("long") / "long.mcap"
    return make_recording(path, seconds=12.0, seed=3, wave=2, object="can_empty")


def start_up(recording: Path, out: Path, port: int) -> subprocess.Popen:
    return spawn(wavegrasp_cmd("up", str(recording), "--pace", "realtime", "--out", str(out)),
                 {"WAVEGRASP_ROUTER_PORT": str(port)}, stdout=subprocess.PIPE,
                 stderr=subprocess.STDOUT)


def connect(port: int) -> Bus:
    # No shared memory: it sends nothing large, and its segment would outlive the run.
    return Bus(Settings.from_env("fuzzer", env={"ZENOH_CONNECT": f"tcp/127.0.0.1:{port}"},
                                 connect_timeout_s=30, shared_memory_mb=0))


def keys_to_fuzz(subscriptions: list[str]) -> list[str]:
    """Every concrete key a service's subscriptions cover (``**`` covers the whole contract)."""
    contract = [*KEY_TYPES, *ROS_KEYS, ack_key("recorder"), stats_key("perception")]
    keys = []
    for sub in subscriptions:
        keys += contract if sub == "**" else [sub]
    return sorted(set(keys))


def test_garbage_on_every_subscribed_key_is_counted(long_recording: Path, tmp_path: Path):
    port = free_port()
    up = start_up(long_recording, tmp_path / "run", port)
    bus = connect(port)
    stats: dict[str, ServiceStats] = {}
    try:
        bus.subscribe("wavegrasp/*/stats", lambda m, d: stats.__setitem__(m.service, m),
                      ServiceStats)

        def pump() -> None:
            while not bus.inbox.empty():
                bus.dispatch(bus.inbox.get())

        services = ["recorder", "perception", "predictor", "planner", "gate", "player"]
        assert wait_until(lambda: (pump(), all(s in stats for s in services))[1], timeout=30)
        sent: dict[str, int] = {}
        for key in sorted({k for s in services for k in keys_to_fuzz(stats[s].subscriptions)}):
            encoding = CDR if key in ROS_KEYS else JSON
            for payload in GARBAGE:
                bus.publish_bytes(key, payload, encoding)
            sent[key] = len(GARBAGE)

        def all_counted() -> bool:
            pump()
            return all(stats[s].bad.get(k, 0) >= sent[k] for s in services
                       for k in keys_to_fuzz(stats[s].subscriptions))

        assert wait_until(all_counted, timeout=10), {s: stats[s].bad for s in services}
        assert not bus.wait_for_services(services, timeout_s=5), "a service died"
    finally:
        bus.close()
    output = up.communicate(timeout=60)[0].decode()
    assert up.returncode == 0, output[-3000:]
    summary = json.loads((tmp_path / "run" / "summary.json").read_text())
    assert summary["bad_messages"]["recorder"]["trisect/points"] >= len(GARBAGE)
    assert summary["player"]["frames"] == 120, "the run went on through the garbage"
    assert "bad messages" in output


def test_ctrl_c_leaves_nothing_behind(long_recording: Path, tmp_path: Path) -> None:
    shm_before = set(os.listdir("/dev/shm"))
    port = free_port()
    up = start_up(long_recording, tmp_path / "run", port)
    bus = connect(port)
    try:
        assert not bus.wait_for_services(["router", "recorder", "player"], timeout_s=30)
    finally:
        bus.close()
    children = psutil.Process(up.pid).children(recursive=True)
    assert len(children) >= 3
    time.sleep(1.0)  # mid-run
    os.kill(up.pid, signal.SIGINT)
    output = up.communicate(timeout=60)[0].decode()
    assert up.returncode == 130, output[-3000:]
    assert wait_until(lambda: not any(c.is_running() and c.status() != psutil.STATUS_ZOMBIE
                                      for c in children), timeout=5)
    with socket.socket() as s:  # nothing listens on the router's port any more
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        s.bind(("127.0.0.1", port))
        s.listen()
    assert set(os.listdir("/dev/shm")) <= shm_before
    # What was recorded until Ctrl-C is in a finished, readable file.
    from mcap.reader import make_reader

    with (tmp_path / "run" / "run.mcap").open("rb") as f:
        summary = make_reader(f).get_summary()
    assert summary is not None and summary.statistics.message_count > 0
    assert json.loads((tmp_path / "run" / "summary.json").read_text())["ended"] == "interrupted"


def test_killed_recorder_loses_at_most_a_second_and_goes_on_in_a_new_file(
        long_recording: Path, tmp_path: Path) -> None:
    """Of what the killed recorder acknowledged, at most a second is lost; what it had
    received and not yet written (a backlog, when the machine is slow) goes with it; its
    successor records every frame from its return, in a new file."""
    from wavegrasp.recording_io.reader import RecordingError, open_recording
    from wavegrasp.schemas import Clock, FrameAck, instance_key

    port = free_port()
    up = start_up(long_recording, tmp_path / "run", port)
    bus = connect(port)
    acked: list[int] = []
    clock: list[tuple[int, int]] = []  # (wall ns at arrival, recording ns)
    appeared: list[int] = []  # wall ns each recorder process's own token appeared
    try:
        bus.subscribe(ack_key("recorder"), lambda m, d: acked.append(m.frame_seq), FrameAck)
        bus.subscribe("wavegrasp/clock", lambda m, d: clock.append((d.recv_ns,
                                                                    m.header.stamp_ns)), Clock)
        tokens = bus.session.liveliness().declare_subscriber(
            instance_key("recorder", "*"), lambda s: appeared.append(time.time_ns())
            if s.kind == zenoh.SampleKind.PUT else None, history=True)

        def pump_until(done) -> bool:
            return wait_until(lambda: (bus.dispatch(bus.inbox.get()) if not bus.inbox.empty()
                                       else None, done())[1], timeout=30)

        assert not bus.wait_for_services(["recorder", "player"], timeout_s=30)
        recorder = next(c for c in psutil.Process(up.pid).children(recursive=True)
                        if "wavegrasp recorder" in " ".join(c.cmdline()))
        assert pump_until(lambda: len(acked) >= 35 and appeared)
        recorder.send_signal(signal.SIGKILL)
        recorder.wait(5)
        assert pump_until(lambda: len(appeared) == 2 and clock[-1][0] > appeared[1])
        tokens.undeclare()
    finally:
        bus.close()
    output = up.communicate(timeout=60)[0].decode()
    assert up.returncode == 0, output[-3000:]
    summary = json.loads((tmp_path / "run" / "summary.json").read_text())
    (restart,) = summary["restarts"]["recorder"]
    assert restart["exit_code"] == -signal.SIGKILL
    assert restart["back_s"] - restart["died_s"] <= 5.0, restart
    frames = 0
    try:
        for m in open_recording(tmp_path / "run" / "run.mcap").messages():
            frames += m.topic == "/trisect/points"
    except RecordingError as exc:
        assert "truncated" in str(exc)
    # Acknowledged frames were written; at most a second (10 frames) of them is lost.
    assert frames >= len(acked) - 10, f"{frames} frames on disk, {len(acked)} acknowledged"
    # The restarted recorder goes on in a new file, to the end of the run, from the frame
    # played when it was back (the recording's clock then; two frames' slack).
    after = [m.log_time_ns for m in open_recording(tmp_path / "run" / "run-1.mcap").messages()
             if m.topic == "/trisect/points"]
    assert after and summary["files"] == ["run-1.mcap", "run.mcap"]
    assert np.allclose(np.diff(after), 100_000_000) and len(after) + frames <= 120, \
        "every frame once, none skipped after the return"
    back_ns = max(stamp for wall, stamp in clock if wall <= appeared[1])
    assert after[0] <= back_ns + 200_000_000, (
        f"the new file begins {(after[0] - back_ns) / 1e9:.1f} s after the recorder was back "
        f"({120 - frames - len(after)} frames missing, {len(acked)} acknowledged before)")


def test_services_stop_together_then_the_late_ones_then_the_router_then_the_last(
        capsys: pytest.CaptureFixture[str]) -> None:
    """Each process says when SIGTERM reached it; the recorder's label (wavegrasp.stop-late)
    keeps it up until the services have stopped, so it records their last counters."""
    program = ("import signal, sys, time\n"
               "def stop(*_):\n"
               "    print('stopped', time.monotonic(), flush=True)\n"
               "    time.sleep(0.6)\n"
               "    sys.exit(0)\n"
               "signal.signal(signal.SIGTERM, stop)\n"
               "print('up', flush=True)\n"
               "while True:\n"
               "    time.sleep(1)\n")
    labels = {"recorder": {"wavegrasp.stop-late": "true"},
              "viewer": {"wavegrasp.stop-last": "true"}}
    services = {name: ComposeService(name, [sys.executable, "-c", program],
                                     labels=labels.get(name, {}))
                for name in ("router", "recorder", "perception", "sim", "viewer")}
    launcher = Launcher(services, {}, fork=False)
    for name in services:
        launcher.start(name)
    time.sleep(1.5)  # every one has installed its handler
    launcher.stop_all()
    out = capsys.readouterr().out
    stopped = {line.split("|")[0].strip(): float(line.split()[-1])
               for line in out.splitlines() if "| stopped" in line}
    assert set(stopped) == set(services), out
    assert stopped["recorder"] > max(stopped["perception"], stopped["sim"]) + 0.5
    assert stopped["router"] > stopped["recorder"] + 0.5
    assert stopped["viewer"] > stopped["router"] + 0.5
    # the services got it together, not one after the other's 0.6 s
    assert abs(stopped["perception"] - stopped["sim"]) < 0.5

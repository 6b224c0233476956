"""``wavegrasp up`` end to end: services as separate processes over zenoh, real MCAP files."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
from mcap.reader import make_reader
from rosbags.highlevel import AnyReader

from wavegrasp.arm import ArmModel
from wavegrasp.ops.forked import forkable
from wavegrasp.recording_io.mcap_read import read_mcap
from wavegrasp.recording_io.own_messages import read_own
from wavegrasp.recording_io.reader import open_recording
from wavegrasp.recording_io.typestore import ros2_typestore
from wavegrasp.recording_io.writer import write_ros1_bag, write_ros2_bag
from wavegrasp.runtime.bus import memory_lock_limit

from conftest import own_messages, recorded, source_frames, wavegrasp_cmd


def run_up(recording: Path, out: Path, pace: str = "fast", timeout: float = 120,
           *extra: str):
    return subprocess.run(wavegrasp_cmd("up", str(recording), "--pace", pace, "--out", str(out),
                                        *extra),
                          capture_output=True, text=True, timeout=timeout)


def check_run(recording: Path, out: Path, result: subprocess.CompletedProcess) -> dict:
    assert result.returncode == 0, result.stdout[-3000:] + result.stderr[-3000:]
    payloads, schemas = recorded(out / "run.mcap")
    expected = source_frames(recording)
    assert len(expected) == 50
    assert payloads["/trisect/points"] == expected, "camera frames must be recorded bit-identical"
    assert schemas["/trisect/points"] == ("sensor_msgs/msg/PointCloud2", "ros2msg")
    assert schemas["/tf_static"] == ("tf2_msgs/msg/TFMessage", "ros2msg")
    assert schemas["/groundtruth/object"] == ("geometry_msgs/msg/PoseStamped", "ros2msg")
    assert schemas["/wavegrasp/clock"] == ("wavegrasp_msgs/msg/Clock", "ros2msg")
    summary = json.loads((out / "summary.json").read_text())
    assert summary["ended"] == "finished" and not summary["crashed"]
    assert summary["player"]["frames"] == 50
    # One timeline, the recording's: what came before its clock started (stats, heartbeats)
    # is logged at its first tick, not on the wall clock (a viewer's timeline spans the file).
    with (out / "run.mcap").open("rb") as f:
        stats = make_reader(f).get_summary().statistics
    with (out / "run.mcap").open("rb") as f:
        ticks = [m.log_time for _, _, m in make_reader(f).iter_messages(["/wavegrasp/clock"])]
    assert stats.message_start_time == min(ticks), (stats.message_start_time, min(ticks))
    assert stats.message_end_time - stats.message_start_time < 60 * 10**9
    # It ends with its table and where to look next (not a terminal: plain status lines).
    assert f"see it: rerun {out / 'run.rrd'}" in result.stdout
    assert "status | " in result.stdout
    return summary


def test_up_fast_records_every_frame_bit_identical(recording: Path, tmp_path: Path) -> None:
    out = tmp_path / "run"
    summary = check_run(recording, out, run_up(recording, out))
    assert summary["bad_messages"] == {}
    # Zenoh handed the clouds on through shared memory once it had set up the player's pool
    # (at its first large message: the first few go over the link meanwhile).
    # None where locked memory is limited (zenoh locks its pools: see memory_lock_limit).
    for name in ("perception", "recorder"):
        shared = summary["services"][name]["received_shared"].get("trisect/points", 0)
        assert shared >= 45 if memory_lock_limit() is None else shared == 0, name
    # The run is itself a recording: the player can replay it.
    replay = open_recording(out / "run.mcap")
    assert set(replay.topics) == {"/trisect/points", "/tf_static", "/groundtruth/object"}
    assert replay.metadata.get("seed") == "7"
    check_ros2_readable(out / "run.mcap")
    check_joint_states(out / "run.mcap")
    # ... and does: the run replayed through the services again.
    again = tmp_path / "again"
    check_run(recording, again, run_up(out / "run.mcap", again))


def check_joint_states(run_mcap: Path) -> None:
    """The sim publishes its joints as a ros2_control arm's driver does, each frame: the
    arm's and the fingers', as ``wavegrasp/sim/arm_state`` has them."""
    states = [ros2_typestore().deserialize_cdr(m.data, "sensor_msgs/msg/JointState")
              for _, _, m in read_mcap(run_mcap, ["/joint_states"])]
    arm = [msg for _, msg, _ in read_own(run_mcap, ["wavegrasp/sim/arm_state"])]
    assert len(states) == len(arm) >= 45  # published together, in order
    model = ArmModel.load()
    n = len(model.joint_names)
    for state, a in zip(states, arm, strict=True):
        assert state.header.stamp.sec * 10**9 + state.header.stamp.nanosec == a.header.stamp_ns
        assert state.name == [*model.joint_names, *model.jaw_joints]
        assert state.position[:n].tolist() == a.positions
        assert state.velocity[:n].tolist() == a.velocities
        assert state.position[n:].sum() == pytest.approx(a.jaw_opening_m)


def check_ros2_readable(run_mcap: Path) -> None:
    """rosbags' AnyReader, the usual Python bag reader, opens the run and decodes every
    message on every channel from the definitions in the file."""
    with run_mcap.open("rb") as f:
        summary = make_reader(f).get_summary()
    in_file = {c.topic: summary.statistics.channel_message_counts[c.id]
               for c in summary.channels.values()}
    with AnyReader([run_mcap]) as reader:
        decoded: dict[str, int] = {}
        for connection, _, raw in reader.messages():
            msg = reader.deserialize(raw, connection.msgtype)
            assert msg.__msgtype__ == connection.msgtype
            decoded[connection.topic] = decoded.get(connection.topic, 0) + 1
    assert decoded == in_file
    assert {"/wavegrasp/perception/object", "/wavegrasp/predictor/prediction",
            "/wavegrasp/sim/arm_state", "/wavegrasp/clock", "/trisect/points",
            "/joint_states"} <= set(decoded)


def test_up_lockstep_acknowledges_each_frame(recording: Path, tmp_path: Path) -> None:
    out = tmp_path / "run"
    check_run(recording, out, run_up(recording, out, pace="lockstep"))
    acks = [m["frame_seq"] for m in own_messages(out / "run.mcap", "wavegrasp/recorder/ack")]
    assert acks == list(range(50))


def test_services_forked_or_started_as_commands_repeat_the_same_lockstep_run(
        recording: Path, tmp_path: Path) -> None:
    """``wavegrasp up`` forks its services from a process that has loaded their libraries;
    ``--no-fork`` starts each as a command, as compose does: the same observations and
    predictions either way (their traces' wall times aside)."""
    def contents(out: Path) -> dict[str, list[dict]]:
        keys = ("wavegrasp/perception/object", "wavegrasp/predictor/prediction")
        got = {key: own_messages(out / "run.mcap", key) for key in keys}
        for messages in got.values():
            for m in messages:
                del m["header"]["trace"]
        return got

    forked, commands = tmp_path / "forked", tmp_path / "commands"
    check_run(recording, forked, run_up(recording, forked, "lockstep"))
    check_run(recording, commands, run_up(recording, commands, "lockstep", 120, "--no-fork"))
    first = contents(forked)
    assert len(first["wavegrasp/perception/object"]) == 50
    assert first["wavegrasp/predictor/prediction"]
    assert first == contents(commands)


def test_only_wavegrasp_services_with_the_servers_thread_limits_are_forked() -> None:
    env = dict(os.environ)
    service = [sys.executable, "-m", "wavegrasp", "perception", "--x"]
    assert forkable(service, env) == ["perception", "--x"]
    assert forkable([sys.executable, "-m", "wavegrasp", "router"], env) == ["router"]
    assert forkable([sys.executable, "-m", "wavegrasp", "viewer"], env) is None
    assert forkable(["rerun", "--serve"], env) is None
    threads = env.get("OMP_NUM_THREADS", "1")
    assert forkable(service, {**env, "OMP_NUM_THREADS": threads + "0"}) is None


@pytest.mark.parametrize("kind", ["ros1", "ros2"])
def test_up_replays_ros_bags(kind: str, recording: Path, tmp_path: Path) -> None:
    messages = list(open_recording(recording).messages())
    if kind == "ros1":
        bag = write_ros1_bag(tmp_path / "input.bag", messages)
    else:
        bag = write_ros2_bag(tmp_path / "input_bag", messages)
    assert open_recording(bag).format == kind
    out = tmp_path / "run"
    check_run(recording, out, run_up(bag, out))


@pytest.mark.parametrize("content,problem", [
    (None, "no such file"),
    (b"hello, this is not a recording\n", "not an MCAP file"),
    (b"", "empty"),
])
def test_bad_recording_gets_a_clear_error(content, problem, tmp_path: Path) -> None:
    path = tmp_path / "input.mcap"
    if content is not None:
        path.write_bytes(content)
    result = subprocess.run(wavegrasp_cmd("player", str(path)), capture_output=True, text=True,
                            timeout=60)
    assert result.returncode == 2
    assert str(path) in result.stderr and problem in result.stderr
    assert "Traceback" not in result.stderr


def test_truncated_recording_names_the_file(recording: Path, tmp_path: Path) -> None:
    cut = tmp_path / "cut.mcap"
    data = recording.read_bytes()
    cut.write_bytes(data[: len(data) * 4 // 5])  # past the first complete chunk
    out = tmp_path / "run"
    result = run_up(cut, out)
    # Warned up front and by the player at the cut; what could be played was: a finished run.
    assert result.returncode == 0, result.stdout[-3000:] + result.stderr[-2000:]
    assert str(cut) in result.stderr and "truncated" in result.stderr
    assert f"wavegrasp player: warning: {cut}" in result.stdout
    assert "Traceback" not in result.stdout + result.stderr
    # What was replayed before the cut is still recorded, in a readable file.
    payloads, _ = recorded(out / "run.mcap")
    assert 0 < len(payloads["/trisect/points"]) < 50
    assert payloads["/trisect/points"] == source_frames(recording)[: len(
        payloads["/trisect/points"])]


def test_mistakes_get_one_line_and_exit_2(recording: Path, tmp_path: Path) -> None:
    """What a user gets wrong is named in one line before anything starts: a predictor that
    does not exist, an arm description that does not load, a port taken, a recording whose
    camera has no transform."""
    import socket

    import numpy as np

    from wavegrasp.recording_io.writer import RecordingWriter

    no_tf = tmp_path / "no_tf.mcap"
    with RecordingWriter(no_tf, {}) as w:
        for i in range(30):
            w.write_points(10**9 + i * 10**8, np.random.default_rng(i).random((100, 3)))
    taken = socket.socket()
    taken.bind(("127.0.0.1", 0))
    port = taken.getsockname()[1]
    cases = [
        ([str(recording), "--predictor", "kalman"], {},
         "--predictor kalman: no such predictor (there are blend, harmonic, linear)"),
        ([str(recording)], {"WAVEGRASP_ARM_URDF": str(tmp_path / "arm.urdf")},
         f"WAVEGRASP_ARM_URDF: arm URDF '{tmp_path / 'arm.urdf'}' does not exist"),
        ([str(recording)], {"WAVEGRASP_ROUTER_PORT": str(port)},
         f"WAVEGRASP_ROUTER_PORT {port}: the port is taken"),
        ([str(no_tf)], {}, f"{no_tf}: no /tf_static transform from the camera's frame "
         "'trisect_optical' to 'world'"),
        ([str(tmp_path / "nowhere.mcap")], {}, f"{tmp_path / 'nowhere.mcap'}: no such file"),
    ]
    try:
        for args, env, line in cases:
            out = tmp_path / f"run-{len(line)}"
            result = subprocess.run(wavegrasp_cmd("up", *args, "--out", str(out)),
                                    capture_output=True, text=True, timeout=60,
                                    env={**os.environ, **env})
            assert result.returncode == 2, (args, result.stdout[-2000:], result.stderr)
            lines = result.stderr.strip().splitlines()
            assert len(lines) == 1 and lines[0].startswith(f"wavegrasp up: {line}"), lines
            assert not (out / "summary.json").exists()  # nothing ran
    finally:
        taken.close()


LIBRARIES = Path("/usr/lib/x86_64-linux-gnu")


@pytest.mark.skipif(os.geteuid() != 0 or not (LIBRARIES / "libusb-1.0.so.0").exists(),
                    reason="hiding a system library needs root (a mount namespace)")
def test_a_missing_system_library_is_named_with_its_package(tmp_path: Path) -> None:
    """open3d's wheel loads libusb from the system: without it a service and `wavegrasp up`
    name it in one line with the Debian package that has it, and exit 2 before anything
    runs. The library is hidden by an overlay (a whiteout) in a mount namespace of the
    commands' own; the machine's stays as it is."""
    upper, work = tmp_path / "upper", tmp_path / "work"
    upper.mkdir()
    work.mkdir()
    os.mknod(upper / "libusb-1.0.so.0", 0o600 | 0o020000, os.makedev(0, 0))  # a whiteout
    mount = (f"mount -t overlay overlay -o lowerdir={LIBRARIES},upperdir={upper},"
             f"workdir={work} {LIBRARIES}")
    recording = Path(__file__).parents[1] / "recordings" / "wave1-buoy-5s.mcap"
    out = tmp_path / "run"
    for command in (wavegrasp_cmd("perception"),
                    wavegrasp_cmd("up", str(recording), "--out", str(out))):
        result = subprocess.run(["unshare", "--mount", "--propagation", "private", "sh", "-c",
                                 f'{mount} && exec "$@"', "sh", *command],
                                capture_output=True, text=True, timeout=120)
        lines = result.stderr.strip().splitlines()
        assert result.returncode == 2, (command, result.stdout[-2000:], result.stderr[-2000:])
        assert len(lines) == 1 and lines[0].endswith(
            "the system library libusb-1.0.so.0 is missing (open3d and PyBullet need it): "
            "install it, e.g. `sudo apt-get install libusb-1.0-0`, or run "
            "`bash ops/setup.sh`"), lines
    assert not out.exists()  # nothing ran


def test_only_a_missing_shared_object_is_taken_for_a_system_library() -> None:
    from wavegrasp.cli import system_library

    assert system_library(OSError("libgomp.so.1: cannot open shared object file: No such "
                                  "file or directory")) == "libgomp.so.1"
    assert system_library(ImportError("No module named 'open3d'")) is None

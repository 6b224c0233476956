"""The shared runtime's pieces driven directly: settings, clock, and a service's handlers."""

from __future__ import annotations

import contextlib
import json
import queue
import signal
import sys
import time
import warnings
from pathlib import Path

import numpy as np
import pytest
from mcap.reader import make_reader

from wavegrasp.arm import ArmModel
from wavegrasp.player.main import PlayerSettings
from wavegrasp.recorder.main import Recorder, RecorderSettings
from wavegrasp.recorder.rerun_log import RerunLog
from wavegrasp.recording_io.reader import open_recording
from wavegrasp.runtime.bus import CDR, JSON, Bus, Delivery, decode_model
from wavegrasp.runtime.clock import RecordingClock
from wavegrasp.runtime.heartbeat import Heartbeat
from wavegrasp.runtime.service import STOP_SIGNALS, Service
from wavegrasp.runtime.settings import Settings
from wavegrasp.runtime.state import PAGE, StateFile
from wavegrasp.runtime.trace import CdrAttachment, derived_header, new_header
from wavegrasp.schemas import (
    ROS_KEYS,
    ArmState,
    Clock,
    FrameAck,
    GraspOutcome,
    Header,
    PlayerStatus,
    ServiceStats,
)

from conftest import Router


def test_settings_from_env_parse_lists_and_name_bad_variables() -> None:
    env = {"ZENOH_CONNECT": "tcp/a:1, tcp/b:2", "WAVEGRASP_PACE": "lockstep",
           "WAVEGRASP_WAIT_FOR": "recorder,gate"}
    s = PlayerSettings.from_env("player", env=env)
    assert s.zenoh_connect == ["tcp/a:1", "tcp/b:2"]
    assert s.pace == "lockstep" and s.wait_for == ["recorder", "gate"]
    assert PlayerSettings.from_env("player", env=env, pace="fast").pace == "fast"
    with pytest.raises(ValueError, match="WAVEGRASP_PACE"):
        PlayerSettings.from_env("player", env={"WAVEGRASP_PACE": "warp"})


def test_clock_follows_ticks_and_scales_with_rate() -> None:
    clock = RecordingClock()
    before = time.time_ns()
    assert clock.now_ns() >= before and not clock.started  # wall until the first tick
    clock.on_clock(Clock(header=Header(stamp_ns=5_000_000_000), rate=0.0))
    time.sleep(0.01)
    assert clock.now_ns() == 5_000_000_000  # frozen between lockstep ticks
    clock.on_clock(Clock(header=Header(stamp_ns=6_000_000_000), rate=1.0))
    time.sleep(0.02)
    assert 6_000_000_000 + 10**7 < clock.now_ns() < 6_000_000_000 + 10**9


def test_trace_grows_one_hop_per_service() -> None:
    h = new_header("player", seq=3, stamp_ns=42)
    h2 = derived_header(h, "perception", recv_ns=h.trace[0].recv_ns + 1)
    assert [x.service for x in h2.trace] == ["player", "perception"]
    assert h2.stamp_ns == 42 and h2.seq == 3 and len(h.trace) == 1


@pytest.fixture
def isolated_bus(request: pytest.FixtureRequest):
    """A real zenoh session that talks to no one: handlers are driven by hand."""
    bus = Bus(Settings(service=request.param, zenoh_mode="peer", zenoh_connect=[],
                       zenoh_listen=[]))
    yield bus
    bus.close()


def recorder_deliveries(bus: Bus, recording: Path) -> tuple[list, list[Delivery]]:
    """A clock tick, three camera frames and a corrupt one, as the recorder's subscription
    hands them over."""
    frames = [m for m in open_recording(recording).messages() if m.topic == "/trisect/points"]
    route = len(bus.subscriptions) - 1  # the recorder's "**" subscription
    clock = Clock(header=Header(stamp_ns=frames[0].log_time_ns))
    deliveries = [Delivery("wavegrasp/clock", clock.model_dump_json().encode(), f"{JSON};Clock",
                           None, 0, route)]
    for seq, m in enumerate(frames[:3]):
        att = CdrAttachment(seq, 0, bytes(16), m.log_time_ns).encode()
        deliveries.append(Delivery("trisect/points", m.cdr, f"{CDR};{m.msgtype}", att, 0, route))
    deliveries.append(Delivery("trisect/points", b"\x00\x01\x00\x00junk", CDR, None, 0, route))
    return frames, deliveries


def recorder_acks(bus: Bus, count: int) -> list[int]:
    """The frames the recorder acknowledged: its acknowledgements come back to it through
    its "**" subscription."""
    acks: list[int] = []
    while len(acks) < count:
        d = bus.inbox.get(timeout=5.0)
        if d.key == "wavegrasp/recorder/ack":
            acks.append(decode_model(d, FrameAck).frame_seq)
    return acks


@pytest.mark.parametrize("isolated_bus", ["recorder"], indirect=True)
def test_recorder_handlers_driven_directly(isolated_bus: Bus, recording: Path,
                                           tmp_path: Path) -> None:
    rec = Recorder(RecorderSettings(service="recorder", out=tmp_path), bus=isolated_bus)
    frames, deliveries = recorder_deliveries(isolated_bus, recording)
    assert [isolated_bus.dispatch(d) for d in deliveries] == [True] * 4 + [False]
    assert rec.frames == 3 and isolated_bus.bad["trisect/points"] == 1
    rec.on_stop()
    with rec.path.open("rb") as f:
        got = [(c.topic, msg.log_time, msg.data)
               for _, c, msg in make_reader(f).iter_messages(log_time_order=False)]
    points = [g for g in got if g[0] == "/trisect/points"]
    assert [p[2] for p in points] == [m.cdr for m in frames[:3]]
    assert [p[1] for p in points] == [m.log_time_ns for m in frames[:3]]
    assert ("wavegrasp/clock", frames[0].log_time_ns, deliveries[0].payload) in got


@pytest.mark.parametrize("isolated_bus", ["recorder"], indirect=True)
def test_recorder_leaves_out_excluded_keys_but_acknowledges_frames(
        isolated_bus: Bus, recording: Path, tmp_path: Path) -> None:
    settings = RecorderSettings.from_env(
        "recorder", {"WAVEGRASP_RECORD_EXCLUDE": "trisect/*"}, out=tmp_path)
    rec = Recorder(settings, bus=isolated_bus)
    frames, deliveries = recorder_deliveries(isolated_bus, recording)
    for d in deliveries:
        isolated_bus.dispatch(d)
    assert rec.frames == 3
    assert recorder_acks(isolated_bus, 3) == [0, 1, 2]
    rec.on_stop()
    with rec.path.open("rb") as f:
        topics = {c.topic for _, c, _ in make_reader(f).iter_messages(log_time_order=False)}
    assert topics == {"wavegrasp/clock"}


@pytest.mark.parametrize("isolated_bus", ["recorder"], indirect=True)
def test_the_recorder_writes_one_cloud_in_cloud_every_and_acknowledges_them_all(
        isolated_bus: Bus, recording: Path, tmp_path: Path) -> None:
    settings = RecorderSettings.from_env("recorder", {
        "WAVEGRASP_CLOUD_EVERY": "2", "WAVEGRASP_MCAP_COMPRESSION": "lz4"}, out=tmp_path,
        rrd=False)
    rec = Recorder(settings, bus=isolated_bus)
    frames, deliveries = recorder_deliveries(isolated_bus, recording)
    for d in deliveries:
        isolated_bus.dispatch(d)
    # The junk frame falls on a cloud left out: like an excluded key's, it is not read.
    assert rec.frames == 3 and not isolated_bus.bad
    assert recorder_acks(isolated_bus, 3) == [0, 1, 2]
    rec.on_stop()
    with rec.path.open("rb") as f:
        reader = make_reader(f)
        points = [msg.data for _, c, msg in reader.iter_messages(log_time_order=False)
                  if c.topic == "/trisect/points"]
        f.seek(0)
        compressions = {c.compression for c in reader.get_summary().chunk_indexes}
    assert points == [frames[0].cdr, frames[2].cdr]  # the first, then every second
    assert compressions == {"lz4"}


@pytest.mark.parametrize("isolated_bus", ["recorder"], indirect=True)
def test_the_recorder_subscribes_only_to_its_record_keys_and_gets_each_clock_tick_once(
        isolated_bus: Bus, tmp_path: Path) -> None:
    """What it does not subscribe to never reaches it (the experiment leaves the 100 Hz ground
    truth out); its own subscription, not a second one, brings its clock."""
    settings = RecorderSettings.from_env("recorder", {
        "WAVEGRASP_RECORD_KEYS": "wavegrasp/**,trisect/points"}, out=tmp_path, rrd=False)
    rec = Recorder(settings, bus=isolated_bus)
    assert isolated_bus.subscriptions == ["wavegrasp/**", "trisect/points"]
    truth = "groundtruth/object"
    isolated_bus.publish_cdr(truth, b"\x00\x01\x00\x00", ROS_KEYS[truth])
    isolated_bus.publish("wavegrasp/clock", Clock(header=Header(stamp_ns=123_000_000_000),
                                                  rate=0.0))
    keys = []
    with contextlib.suppress(queue.Empty):
        while True:
            d = isolated_bus.inbox.get(timeout=1.0)
            keys.append(d.key)
            assert isolated_bus.dispatch(d)
    assert keys == ["wavegrasp/clock"]
    assert rec.clock.now_ns() == 123_000_000_000
    rec.on_stop()


@pytest.mark.parametrize("isolated_bus", ["recorder"], indirect=True)
def test_recorder_writes_the_runs_summary_when_it_stops(isolated_bus: Bus,
                                                        tmp_path: Path) -> None:
    """Under docker compose no launcher sees the run: the recorder's summary.json says how it
    went, bad messages added up across a service's restart."""
    rec = Recorder(RecorderSettings(service="recorder", out=tmp_path, rrd=False),
                   bus=isolated_bus)
    route = len(isolated_bus.subscriptions) - 1

    def deliver(key: str, msg) -> None:
        payload = msg.model_dump_json().encode()
        assert isolated_bus.dispatch(Delivery(key, payload, JSON, None, 0, route))

    deliver("wavegrasp/perception/stats", ServiceStats(
        header=Header(), service="perception", bad={"trisect/points": 2}, uptime_s=30.0))
    deliver("wavegrasp/perception/stats", ServiceStats(  # restarted: its counts start again
        header=Header(), service="perception", bad={"trisect/points": 1}, uptime_s=1.0))
    deliver("wavegrasp/sim/outcome", GraspOutcome(
        header=Header(), plan_id="p1", trial=0, attempt=1, success=False, failure="timing"))
    deliver("wavegrasp/sim/outcome", GraspOutcome(
        header=Header(), plan_id="p2", trial=0, attempt=2, success=True))
    deliver("wavegrasp/player/status", PlayerStatus(
        header=Header(), state="finished", recording="recordings/x.mcap", pace="lockstep",
        frames=160))
    rec.on_stop()
    summary = json.loads((tmp_path / "summary.json").read_text())
    assert summary["ended"] == "finished" and summary["player"]["frames"] == 160
    assert summary["recording"] == "recordings/x.mcap" and summary["files"] == ["run.mcap"]
    assert [(o["plan_id"], o["success"], o["failure"]) for o in summary["outcomes"]] == [
        ("p1", False, "timing"), ("p2", True, None)]
    assert summary["bad_messages"] == {"perception": {"trisect/points": 3}}


def test_heartbeat_is_touched_only_while_the_bus_reaches_a_router(router: Router,
                                                                   tmp_path: Path) -> None:
    """Compose's healthcheck reads the file's age: no file while a client has no router."""
    alone = Bus(Settings(service="alone", zenoh_mode="peer", zenoh_connect=[], zenoh_listen=[]))
    connected = router.bus("connected")
    try:
        Heartbeat(tmp_path / "alone").beat(alone)
        assert not (tmp_path / "alone").exists()
        beat = Heartbeat(tmp_path / "up", period_s=60.0)
        beat.beat(connected)
        first = (tmp_path / "up").stat().st_mtime_ns
        time.sleep(0.02)
        beat.beat(connected)  # within its period: not touched again
        assert (tmp_path / "up").stat().st_mtime_ns == first
    finally:
        alone.close()
        connected.close()


def test_recorder_rejects_a_bad_exclude_expression(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="WAVEGRASP_RECORD_EXCLUDE"):
        RecorderSettings.from_env("recorder", {"WAVEGRASP_RECORD_EXCLUDE": "a//b"}, out=tmp_path)


def test_recorder_refuses_record_keys_that_overlap(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="WAVEGRASP_RECORD_KEYS.*overlap"):
        RecorderSettings.from_env("recorder", {
            "WAVEGRASP_RECORD_KEYS": "wavegrasp/**,wavegrasp/clock"}, out=tmp_path)


def test_the_service_loop_holds_the_interpreter_lock_as_briefly_as_its_settings_say(
        router: Router) -> None:
    class Probe(Service):
        seen = 0.0

        def on_tick(self) -> None:
            self.seen = sys.getswitchinterval()
            self.stop()

    before = sys.getswitchinterval()
    handlers = {sig: signal.getsignal(sig) for sig in STOP_SIGNALS}
    try:
        probe = Probe(Settings.from_env("probe", env={**router.env,
                                                      "WAVEGRASP_SWITCH_INTERVAL_MS": "0.25"}))
        assert probe.run() == 0
    finally:
        sys.setswitchinterval(before)
        for sig, handler in handlers.items():
            signal.signal(sig, handler)
    assert probe.seen == pytest.approx(0.00025)
    assert Settings(service="x").switch_interval_ms == 0.5  # Python's own default is 5 ms


def test_the_rerun_log_keeps_an_arm_state_on_its_joint_limits_without_warning(
        tmp_path: Path) -> None:
    arm = ArmModel.load(None)
    log = RerunLog(tmp_path / "run.rrd", arm.urdf_path)
    state = ArmState(header=new_header("sim", 1, 1_000_000_000), joint_names=arm.joint_names,
                     positions=arm.q_home.tolist(), jaw_opening_m=0.14 + 1e-9)  # wide open
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # rerun's own clamp warns at every state
        log.arm_state(state)
    log.close()
    assert (tmp_path / "run.rrd").stat().st_size > 0


def test_a_state_file_is_overwritten_in_place_and_always_whole(tmp_path) -> None:
    path = tmp_path / "state.json"
    state = StateFile(path)
    state.save({"frames": 1, "note": "x" * 100})
    inode = path.stat().st_ino
    state.save({"frames": 2})  # shorter: the rest of the page is blank, still one JSON object
    assert path.stat().st_ino == inode and path.stat().st_size == PAGE
    assert StateFile(path).load() == {"frames": 2}
    state.save({"frames": 3, "note": "y" * PAGE})  # over a page: a new file renamed in
    assert path.stat().st_ino != inode
    assert StateFile(path).load() == {"frames": 3, "note": "y" * PAGE}
    state.save({"frames": 4})
    assert StateFile(path).load() == {"frames": 4}
    state.clear()
    assert not path.exists() and StateFile(path).load() is None


def test_the_recorder_writes_every_cloud_of_a_small_camera_and_thins_a_big_one() -> None:
    from wavegrasp.recorder.thinning import SAMPLE, CloudThinner

    small = CloudThinner(0, budget_mb_s=20.0)  # 30 000 points at 10 Hz: 5 MB/s
    assert all(small.keep(480_000, i * 100_000_000) for i in range(100))
    assert small.every == 1
    big = CloudThinner(0, budget_mb_s=20.0)  # 8 MB organized clouds at 30 Hz: 243 MB/s
    kept = [i for i in range(SAMPLE + 40) if big.keep(8_085_645, i * 33_333_333)]
    assert big.every == 13 and big.rate_mb_s == pytest.approx(242.6, abs=0.1)
    assert kept == [*range(SAMPLE), SAMPLE, SAMPLE + 13, SAMPLE + 26, SAMPLE + 39]
    fixed = CloudThinner(3, budget_mb_s=20.0)
    assert [i for i in range(10) if fixed.keep(8_085_645, i)] == [0, 3, 6, 9]
    with pytest.raises(ValueError, match="cloud_every"):
        CloudThinner(-1, 20.0)


@pytest.mark.parametrize("isolated_bus", ["player"], indirect=True)
def test_a_looped_recording_plays_on_as_one_stream(isolated_bus: Bus, recording: Path) -> None:
    """``loops``: each loop follows the last a frame later, every time moved on alike (log
    time and the header stamps the services read); static transforms keep theirs."""
    from wavegrasp.player.main import Player
    from wavegrasp.recording_io.reader import open_for_replay
    from wavegrasp.recording_io.ros_msgs import decode_points, decode_pose

    player = Player(PlayerSettings(service="player", loops=3), open_for_replay(recording),
                    bus=isolated_bus)
    once = list(player.recording.messages())
    looped = list(player.looped())
    assert len(looped) == 3 * len(once)
    times = [m.log_time_ns for m in looped]
    assert times == sorted(times)
    frames = [m for m in looped if m.topic == "/trisect/points"]
    assert len(frames) == 150  # 50 a loop
    gaps = np.diff([m.log_time_ns for m in frames])
    # A frame period throughout; where a loop meets the next, at most one more (the ground
    # truth's last messages come after the last frame, and time never runs back).
    assert (gaps == 100_000_000).sum() == len(gaps) - 2
    assert (gaps[[49, 99]] >= 100_000_000).all() and (gaps[[49, 99]] <= 200_000_000).all()
    for m in frames:
        assert decode_points(m.cdr).stamp_ns == m.log_time_ns
        assert decode_points(m.cdr).points.tobytes() == decode_points(
            once[looped.index(m) % len(once)].cdr).points.tobytes()
    truth = [m for m in looped if m.topic == "/groundtruth/object"]
    assert all(decode_pose(m.cdr)[2] == m.log_time_ns for m in truth)
    tf = [m for m in looped if m.topic == "/tf_static"]
    assert len({m.cdr for m in tf}) == len({m.cdr for m in once if m.topic == "/tf_static"})


@pytest.mark.parametrize("isolated_bus", ["recorder"], indirect=True)
def test_what_comes_before_the_clock_is_logged_at_its_first_tick(
        isolated_bus: Bus, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """One timeline: a service's stats that arrive before the replay's first tick are logged
    at that tick; with no tick in time (a live run without ``clock: wall``) at their arrival,
    not held in memory for ever."""
    from wavegrasp.recorder import main as recorder_main

    def stats(uptime_s: float) -> Delivery:
        msg = ServiceStats(header=new_header("gate", 1, time.time_ns()), service="gate",
                           uptime_s=uptime_s)
        return Delivery("wavegrasp/gate/stats", msg.model_dump_json().encode(),
                        f"{JSON};ServiceStats", None, 0, len(isolated_bus.subscriptions) - 1)

    def log_times(rec: Recorder) -> list[int]:
        rec.on_stop()
        with rec.path.open("rb") as f:
            return [m.log_time for _, _, m in make_reader(f).iter_messages(log_time_order=False)]

    tick_ns = 1_700_000_000 * 10**9
    rec = Recorder(RecorderSettings(service="recorder", out=tmp_path / "a", rrd=False),
                   bus=isolated_bus)
    clock = Clock(header=Header(stamp_ns=tick_ns))
    for d in (stats(1.0), stats(2.0), Delivery(
            "wavegrasp/clock", clock.model_dump_json().encode(), f"{JSON};Clock", None, 0,
            len(isolated_bus.subscriptions) - 1), stats(3.0)):
        isolated_bus.dispatch(d)
    times = log_times(rec)
    assert len(times) == 4 and times[:3] == [tick_ns] * 3 and times[3] - tick_ns < 10**9
    monkeypatch.setattr(recorder_main, "EARLY_WAIT_NS", 0)  # no tick comes in time
    rec = Recorder(RecorderSettings(service="recorder", out=tmp_path / "b", rrd=False),
                   bus=isolated_bus)
    before = time.time_ns()
    isolated_bus.dispatch(stats(1.0))
    isolated_bus.dispatch(stats(2.0))
    assert rec._early is None  # none held any more
    times = log_times(rec)
    assert len(times) == 2 and all(before <= t <= time.time_ns() for t in times)

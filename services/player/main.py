"""``wavegrasp player [RECORDING]``: replay a recording over the bus.

Reads MCAP (ROS 2 profile), ROS 1 ``.bag`` files and ROS 2 bag folders and publishes
``/trisect/points``, ``/tf_static`` and ``/groundtruth/object`` on keys ``trisect/points``,
``tf_static`` and ``groundtruth/object`` with their CDR bytes unchanged and an attachment
(sequence, source timestamp, log time), and the recording's time on ``wavegrasp/clock``.

Pacing: ``realtime`` keeps the recording's rate; ``fast`` goes as fast as the bus takes it;
``lockstep`` waits after each camera frame until every service in ``ack_services`` has
acknowledged it on ``wavegrasp/<service>/ack``, so a run is deterministic. In every pacing the
player waits at the end for the last frame's acknowledgement (bounded by ``ack_timeout_s``)
so nothing is cut off when the run stops.

With ``resume_file`` (``WAVEGRASP_RESUME_FILE``) the player notes after each camera frame how
far it got; started again on the same recording (compose restarts it after a crash) it goes on
after that frame, its sequence numbers carrying on. Static transforms are sent again every
2 s of recording time when the recording does not repeat them (a ROS bag latches them once),
so a service that restarts mid-run gets them.

A file that is no recording, or none the pipeline can run on (no ``/trisect/points`` point
clouds), gets one line on stderr naming it and the problem, and exit code 2. One that can be
read only in part (cut short, as a killed recorder leaves it, or with a corrupt chunk) is
played up to where it breaks, with a warning naming the file and the problem; the replay then
ends as finished (exit 0): what could be played was.
"""

from __future__ import annotations

import argparse
import logging
import sys
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Literal

from pydantic import Field, field_validator

from wavegrasp.ops.sample import default_recording
from wavegrasp.recording_io.reader import (
    RecordedMessage,
    Recording,
    RecordingError,
    open_for_replay,
)
from wavegrasp.recording_io.ros_msgs import ROS_CLOCK, encode_clock
from wavegrasp.runtime.bus import Bus, Delivery
from wavegrasp.runtime.service import Service, setup_logging
from wavegrasp.runtime.settings import Settings
from wavegrasp.runtime.state import StateFile
from wavegrasp.runtime.trace import new_header
from wavegrasp.schemas import CLOCK_KEY, Clock, FrameAck, PlayerStatus, ack_key

log = logging.getLogger("wavegrasp.player")
POINTS_TOPIC = "/trisect/points"
TF_STATIC_TOPIC = "/tf_static"
#: Static transforms are sent again when the recording has not for this long (recording
#: time): ROS latches them, and a service that (re)starts mid-run needs them. Ours repeat
#: them every second.
TF_STATIC_PERIOD_NS = 2_000_000_000
Pace = Literal["realtime", "fast", "lockstep"]


class PlayerSettings(Settings):
    recording: Path | None = Field(None, description="what to replay when the command line "
                                   "names nothing; unset or empty: the sample, generated into "
                                   "the cache on first use")
    pace: Pace = "realtime"
    ack_services: list[str] = Field(default_factory=lambda: ["recorder"],
                                    description="whose FrameAcks end a frame in lockstep")
    ack_timeout_s: float = Field(30.0, gt=0)
    clock_period_s: float = Field(0.1, ge=0, description="least recording time between "
                                  "clock ticks, besides the one before every camera frame")
    ros_clock_key: str = Field("", description="if set (ROS 2's is 'clock'), each tick also "
                               "goes there as rosgraph_msgs/msg/Clock, the time of ROS 2 nodes "
                               "with use_sim_time (a real arm's controllers during a replay); "
                               "off by default: a message more a frame for every run")
    wait_for: list[str] = Field(default_factory=list,
                                description="services whose liveliness to await before playing")
    wait_timeout_s: float = Field(30.0, gt=0)
    loops: int = Field(1, ge=1, description="play the recording this many times, each "
                       "after the last with every time (log time, header stamps) moved on "
                       "by the recording's length and one frame: one stream as long as the "
                       "loops (a soak)")
    resume_file: Path | None = Field(None, description="where the player notes how far it "
                                     "got after each camera frame; a restarted player "
                                     "resumes from there (same recording only)")

    @field_validator("recording", mode="before")
    @classmethod
    def empty_is_unset(cls, value: object) -> object:
        return value or None


class Player(Service):
    subscribes_clock = False  # it makes the clock

    def __init__(self, settings: PlayerSettings, recording: Recording,
                 bus: Bus | None = None) -> None:
        super().__init__(settings, bus)
        self.cfg = settings
        self.recording = recording
        self.frames = 0
        self.messages = 0
        self.acked = {name: -1 for name in settings.ack_services}
        self._clock_seq = 0
        self._last_clock_ns: int | None = None
        self._tf_static: RecordedMessage | None = None
        self.state = StateFile(settings.resume_file)
        self._resolved = str(self.recording.path.resolve())
        self._tf_static_sent_ns = 0
        for name in settings.ack_services:
            self.bus.subscribe(ack_key(name), self.on_ack, FrameAck)

    def on_ack(self, msg: FrameAck, _d: Delivery) -> None:
        if msg.service in self.acked:
            self.acked[msg.service] = max(self.acked[msg.service], msg.frame_seq)

    @property
    def acked_seq(self) -> int:
        """The newest frame every service in ``ack_services`` has acknowledged."""
        return min(self.acked.values(), default=-1)

    def status(self, state: str, error: str | None = None) -> None:
        self.bus.publish("wavegrasp/player/status", PlayerStatus(
            header=new_header(self.name, self.frames, self._last_clock_ns or 0),
            state=state, recording=str(self.recording.path), pace=self.cfg.pace,
            frames=self.frames, messages=self.messages, metadata=self.recording.metadata,
            error=error))

    def publish_clock(self, stamp_ns: int, frame: bool = False) -> None:
        """The recording's time, before every camera frame and otherwise at most every
        ``clock_period_s`` (every service decodes every tick: a 10 Hz camera makes the
        ticks, and 100 Hz ground truth between its frames makes none)."""
        if self._last_clock_ns is not None and (stamp_ns <= self._last_clock_ns or (
                not frame and stamp_ns - self._last_clock_ns < self.cfg.clock_period_s * 1e9)):
            return
        self._last_clock_ns = stamp_ns
        self._clock_seq += 1
        rate = {"realtime": 1.0, "fast": 0.0, "lockstep": 0.0}[self.cfg.pace]
        self.bus.publish(CLOCK_KEY, Clock(
            header=new_header(self.name, self._clock_seq, stamp_ns), rate=rate,
            published=self.bus.published()))
        if self.cfg.ros_clock_key:
            self.bus.publish_cdr(self.cfg.ros_clock_key, encode_clock(stamp_ns), ROS_CLOCK)

    def resume_point(self) -> int | None:
        """The log time the last run of this player got to on this recording (None: start
        from the beginning); its sequence numbers carry on from there."""
        state = self.state.load()
        if state is None or state.get("recording") != str(self.recording.path.resolve()):
            return None
        try:
            log_time_ns, published = int(state["log_time_ns"]), dict(state["published"])
            self.frames, self.messages = int(state["frames"]), int(state["messages"])
        except (KeyError, TypeError, ValueError) as exc:
            log.warning("%s: not a player state (%s); playing from the start",
                        self.state.path, exc)
            return None
        self.bus.continue_sequences(published)
        log.warning("resuming %s after %d camera frames (log time %d)", self.recording.path,
                    self.frames, log_time_ns)
        return log_time_ns

    def note_progress(self, log_time_ns: int) -> None:
        self.state.save({"recording": self._resolved,
                         "log_time_ns": log_time_ns, "frames": self.frames,
                         "messages": self.messages, "published": self.bus.published()})

    def latch_tf_static(self, msg: RecordedMessage) -> None:
        """Before ``msg``, send the latest static transforms again if they are due."""
        if msg.topic == TF_STATIC_TOPIC:
            self._tf_static, self._tf_static_sent_ns = msg, msg.log_time_ns
            return
        last = self._tf_static
        if last is not None and msg.log_time_ns - self._tf_static_sent_ns >= TF_STATIC_PERIOD_NS:
            self.bus.publish_cdr(last.topic.lstrip("/"), last.cdr, last.msgtype,
                                 msg.log_time_ns)
            self._tf_static_sent_ns = msg.log_time_ns

    def laggards(self, seq: int) -> str:
        return ", ".join(name for name, acked in self.acked.items() if acked < seq)

    def wait_for_ack(self, seq: int, timeout_s: float) -> bool:
        """Serve the loop until frame ``seq`` is acknowledged; False on timeout or stop."""
        deadline = time.monotonic() + timeout_s
        while self.acked_seq < seq and not self.stopping.is_set():
            if time.monotonic() > deadline:
                return False
            self.step(0.01)
        return self.acked_seq >= seq

    def play(self) -> int:
        """Publish every message of the recording with the chosen pacing; returns exit code."""
        cfg = self.cfg
        if cfg.wait_for:
            missing = self.bus.wait_for_services(cfg.wait_for, cfg.wait_timeout_s)
            if missing:
                log.error("services not alive after %.0f s: %s", cfg.wait_timeout_s,
                          ", ".join(sorted(missing)))
                return 3
        self.status("playing")
        first_ns: int | None = None
        start = time.monotonic()
        last_seq = -1
        resume_ns = self.resume_point()
        for msg in self.looped():
            if self.stopping.is_set():
                break
            if resume_ns is not None and msg.log_time_ns <= resume_ns:
                if msg.topic == TF_STATIC_TOPIC:
                    self._tf_static = msg
                continue
            if first_ns is None:
                first_ns = msg.log_time_ns
            if cfg.pace == "realtime":
                due = start + (msg.log_time_ns - first_ns) / 1e9
                while (wait := due - time.monotonic()) > 0 and not self.stopping.is_set():
                    self.step(min(wait, 0.05))
            else:
                self.drain()
            self.publish_clock(msg.log_time_ns, frame=msg.topic == POINTS_TOPIC)
            self.latch_tf_static(msg)
            seq = self.bus.publish_cdr(msg.topic.lstrip("/"), msg.cdr, msg.msgtype,
                                       msg.log_time_ns)
            self.messages += 1
            if msg.topic == POINTS_TOPIC:
                self.frames += 1
                last_seq = seq
                self.note_progress(msg.log_time_ns)
                if cfg.pace == "lockstep" and not self.wait_for_ack(seq, cfg.ack_timeout_s):
                    if self.stopping.is_set():
                        break
                    log.error("frame %d not acknowledged by %s within %.0f s", seq,
                              self.laggards(seq), cfg.ack_timeout_s)
                    self.status("failed", f"frame {seq} not acknowledged")
                    return 4
        if last_seq >= 0 and not self.stopping.is_set() and not self.wait_for_ack(
                last_seq, cfg.ack_timeout_s):
            log.warning("last frame %d not acknowledged by %s", last_seq,
                        self.laggards(last_seq))
        self.status("finished")
        self.state.clear()  # a finished replay is not resumed
        log.info("played %d messages, %d camera frames from %s in %.1f s", self.messages,
                 self.frames, self.recording.path, time.monotonic() - start)
        return 0

    def looped(self) -> Iterator[RecordedMessage]:
        """The recording's messages ``loops`` times over, each loop after the last (a frame
        period, judged by its last two frames, between them)."""
        offset_ns, span_ns, frame_ns, period_ns = 0, 0, 0, 100_000_000
        for n in range(self.cfg.loops):
            first_ns = None
            for msg in self.recording.messages():
                first_ns = msg.log_time_ns if first_ns is None else first_ns
                span_ns = max(span_ns, msg.log_time_ns - first_ns)
                if msg.topic == POINTS_TOPIC:
                    if 0 < msg.log_time_ns - frame_ns < period_ns * 10:
                        period_ns = msg.log_time_ns - frame_ns
                    frame_ns = msg.log_time_ns
                yield msg.shifted(offset_ns)
            offset_ns += span_ns + period_ns
            if n + 1 < self.cfg.loops:
                log.info("loop %d of %d done: %d camera frames so far", n + 1, self.cfg.loops,
                         self.frames)

    def on_stop(self) -> None:
        self.state.clear()  # stopped, not crashed: the next run starts from the beginning

    def serve(self) -> int:
        if self.recording.problem:  # e.g. cut short: play what is there, then fail at the cut
            log.warning("%s: %s; playing its %s readable messages", self.recording.path,
                        self.recording.problem, self.recording.message_count)
        try:
            return self.play()
        except RecordingError as exc:  # it breaks part-way: what came before was played
            self.status("finished", str(exc))
            self.state.clear()
            print(f"wavegrasp player: warning: {exc}; played {self.frames} camera frames",
                  file=sys.stderr)
            return 0


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="wavegrasp player", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("recording", type=Path, nargs="?",
                        help="MCAP file, ROS 1 .bag or ROS 2 bag folder (default: "
                        "WAVEGRASP_RECORDING, else the sample `wavegrasp up` plays)")
    parser.add_argument("--pace", choices=["realtime", "fast", "lockstep"],
                        help="default: WAVEGRASP_PACE or realtime")
    parser.add_argument("--wait-for", help="services to await, comma-separated")
    args = parser.parse_args(argv)
    try:
        settings = PlayerSettings.from_env(
            "player", pace=args.pace,
            wait_for=args.wait_for.split(",") if args.wait_for else None)
        recording = open_for_replay(args.recording or settings.recording or default_recording())
    except (ValueError, RecordingError) as exc:
        print(f"wavegrasp player: {exc}", file=sys.stderr)
        return 2
    setup_logging(settings.log_level)
    return Player(settings, recording).run()

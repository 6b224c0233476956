"""``wavegrasp recorder``: subscribes to everything and writes ``OUT/run.mcap`` and
``OUT/run.rrd``.

CDR keys, ours (``wavegrasp_msgs``) as well as the camera's, become ROS 2 channels (topic
``/a/b`` for key ``a/b``, ``ros2msg`` schema), so a run is itself a recording the player can
replay and ROS 2 tools read; JSON a tool publishes becomes a ``json`` channel with the model's
JSON Schema. log_time is on the recording's clock (the CDR attachment's log time, else the
latest ``wavegrasp/clock``), so the run lines up with its input; what comes before the
clock's first tick is logged at that tick. The file is flushed every
``flush_period_s``: a killed recorder loses at most that much. After each camera frame is
written the recorder acknowledges it on ``wavegrasp/recorder/ack`` (the player's lockstep).
The recorder subscribes to ``record_keys`` (``WAVEGRASP_RECORD_KEYS``, comma-separated key
expressions; everything by default) and does not write keys matching ``record_exclude``
(``WAVEGRASP_RECORD_EXCLUDE``): ``wavegrasp eval`` records neither the clouds nor the ground
truth its cached input recordings already hold, nor the frame acknowledgements; the clouds
still arrive, because the recorder acknowledges camera frames, and the rest are not
subscribed at all.
Camera clouds are thinned to ``cloud_budget_mb_s`` (:mod:`wavegrasp.recorder.thinning`): a
10 Hz camera's are all written, a 30 Hz organized camera's one in N.
``run.rrd`` is the same run for the rerun viewer (:mod:`wavegrasp.recorder.rerun_log`);
with ``viewer_url`` the recorder also streams it live to a viewer (``wavegrasp viewer``).
"""

from __future__ import annotations

import argparse
import contextlib
import json
import logging
import os
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Literal

import zenoh
from mcap.writer import CompressionType, Writer
from pydantic import BaseModel, Field, field_validator

from wavegrasp.arm import ArmModel
from wavegrasp.recorder.summary import RunSummary
from wavegrasp.recorder.thinning import SAMPLE, CloudThinner
from wavegrasp.recording_io.joint_cdr import (
    JOINT_STATE,
    JOINT_TRAJECTORY,
    parse_joint_state,
    parse_joint_trajectory,
)
from wavegrasp.recording_io.ros_msgs import (
    StaticTransforms,
    decode_points,
    decode_pose,
    decode_tf,
)
from wavegrasp.recording_io.typestore import ros2_msgdef, ros2_typestore
from wavegrasp.runtime.bus import CDR, JSON, BadMessage, Bus, Delivery, cdr_meta, decode_model
from wavegrasp.runtime.service import Service, setup_logging
from wavegrasp.runtime.settings import Settings
from wavegrasp.schemas import (
    CLOCK_KEY,
    MESSAGE_TYPES,
    ROS_KEYS,
    ArmState,
    Clock,
    GateDecision,
    GraspOutcome,
    GraspPlan,
    Header,
    Hop,
    MotionPrediction,
    ObjectObservation,
    PlayerStatus,
    ServiceStats,
    model_for_key,
)
from wavegrasp.schemas.export import schema_text
from wavegrasp.schemas.ros import PACKAGE
from wavegrasp.schemas.ros import msgtype as ros_msgtype

if TYPE_CHECKING:
    from wavegrasp.recorder.rerun_log import RerunLog

log = logging.getLogger("wavegrasp.recorder")
#: The camera's clouds (the default of ``points_key``).
POINTS_KEY = "trisect/points"
OBJECT_POINTS_KEY = "wavegrasp/perception/points"
TRUTH_KEY = "groundtruth/object"


class RecorderSettings(Settings):
    points_key: str = Field(POINTS_KEY, description="the camera's clouds, whose frames "
                            "it acknowledges (across a tether, the edge's)")
    out: Path = Path("out")
    flush_period_s: float = 0.5
    record_keys: list[str] = Field(default_factory=lambda: ["**"],
                                   description="key expressions to subscribe to; include "
                                   "the camera's points (frames are acknowledged on them)")
    record_exclude: list[str] = Field(default_factory=list,
                                      description="key expressions not to write")
    cloud_every: int = Field(0, ge=0, description="write one camera cloud in this many to "
                             "run.mcap and run.rrd (as rosbag2 users throttle a camera; every "
                             "frame is still acknowledged); 0: as many as cloud_budget_mb_s "
                             "allows, judged on the first clouds")
    cloud_budget_mb_s: float = Field(20.0, gt=0, description="with cloud_every 0, the "
                                     "megabytes of camera clouds a second written at most")
    mcap_compression: Literal["zstd", "lz4", "none"] = Field("zstd", description="run.mcap's "
                                                             "chunk compression")
    rrd: bool = Field(True, description="also write run.rrd (rerun) beside run.mcap")
    rrd_minutes: float = Field(10.0, ge=0, description="run.rrd holds this many minutes of "
                               "the run (wall time), then it is closed: rerun's recording "
                               "stream keeps memory for what it has written (about 7 MB a "
                               "minute of the edge stage's clouds, 40 of a camera's full "
                               "ones; rerun-io/rerun#12623), and a long run would run out; "
                               "0: no limit")
    viewer_url: str | None = Field(None, description="also stream the run live to this "
                                   "rerun viewer (rerun+http://HOST:PORT/proxy)")
    arm_urdf: str | None = None

    @field_validator("record_keys", "record_exclude")
    @classmethod
    def check_key_expressions(cls, exprs: list[str]) -> list[str]:
        for expr in exprs:
            try:
                zenoh.KeyExpr(expr)
            except Exception as exc:  # zenoh raises its own error type
                raise ValueError(f"{expr!r} is not a key expression: {exc}") from None
        return exprs

    @field_validator("record_keys")
    @classmethod
    def check_no_overlap(cls, exprs: list[str]) -> list[str]:
        """Each subscription delivers its own copy: overlapping ones would write a message
        twice."""
        keys = [zenoh.KeyExpr(e) for e in exprs]
        for i, a in enumerate(keys):
            for b in keys[i + 1:]:
                if a.intersects(b):
                    raise ValueError(f"{str(a)!r} and {str(b)!r} overlap: what both match "
                                     "would be recorded twice")
        return exprs


def free_run_path(out: Path) -> Path:
    """``out/run.mcap``, or ``run-1.mcap``, ``run-2.mcap`` ... if a run is already there."""
    path, n = out / "run.mcap", 0
    while path.exists():
        n += 1
        path = out / f"run-{n}.mcap"
    return path


#: How long, and how many bytes, messages are held for the clock's first tick (a few
#: seconds of start-up); past either the run has no recording clock (a live one without
#: ``clock: wall``) and they are written at their arrival.
EARLY_WAIT_NS = 5 * 10**9
EARLY_BYTES = 64 * 2**20


class Recorder(Service):
    subscribes_clock = False  # its own subscription brings the ticks: see _record_own

    def __init__(self, settings: RecorderSettings, bus: Bus | None = None) -> None:
        super().__init__(settings, bus)
        settings.out.mkdir(parents=True, exist_ok=True)
        self.path = free_run_path(settings.out)
        self.flush_period_s = settings.flush_period_s
        self.points_key = settings.points_key
        self._file = self.path.open("wb")
        self.writer = Writer(self._file,
                             compression=CompressionType[settings.mcap_compression.upper()])
        self.thinner = CloudThinner(settings.cloud_every, settings.cloud_budget_mb_s)
        self.writer.start(profile="ros2", library="wavegrasp recorder")
        self._schemas: dict[tuple[str, str], int] = {}
        self._channels: dict[str, int] = {}
        self._typestore = ros2_typestore()
        self._last_flush = time.monotonic()
        self._wrote_metadata = False
        #: Messages that came before the recording's clock started (its first tick):
        #: (channel, payload, publish time, sequence, arrival ns), logged at the first
        #: tick's time; None once no tick came in time (they went at their arrival).
        self._early: list[tuple[int, bytes, int, int, int]] | None = []
        self._early_bytes = 0
        self.frames = 0
        self.written = 0
        self.excluded: list[zenoh.KeyExpr] = [zenoh.KeyExpr(e) for e in settings.record_exclude]
        self._skip: dict[str, bool] = {}  # per key: excluded?
        self.rerun: RerunLog | None = None
        self._started_rrd = time.monotonic()
        self.rrd_minutes = settings.rrd_minutes
        if settings.rrd or settings.viewer_url:
            # rerun takes about half a CPU second to import: not for runs that do not use it
            # (the experiment's 36 runs).
            from wavegrasp.recorder.rerun_log import RerunLog

            self.arm = ArmModel.load(settings.arm_urdf or None)
            self.rerun = RerunLog(self.path.with_suffix(".rrd") if settings.rrd else None,
                                  self.arm.urdf_path, settings.viewer_url or None)
        self.tf = StaticTransforms()
        self.summary = RunSummary()
        self._to_summary = {ServiceStats: self.summary.on_stats,
                            PlayerStatus: self.summary.on_status,
                            GraspOutcome: self.summary.on_outcome}
        self._to_rerun = {ObjectObservation: "observation", MotionPrediction: "prediction",
                          GraspPlan: "plan", GateDecision: "decision", ArmState: "arm_state",
                          GraspOutcome: "outcome"}
        for expr in settings.record_keys:
            self.bus.subscribe(expr, self.on_message)
        if not any(zenoh.KeyExpr(e).includes(CLOCK_KEY) for e in settings.record_keys):
            self.bus.subscribe(CLOCK_KEY, self.on_clock, Clock)
        log.info("recording to %s%s", self.path, " and run.rrd" if settings.rrd else "")

    def _channel(self, topic: str, encoding: str, schema_name: str, schema_encoding: str,
                 schema_data: Callable[[], str]) -> int:
        """The channel for ``topic``, registered (with its schema) on first use."""
        channel = self._channels.get(topic)
        if channel is None:
            key = (schema_name, schema_encoding)
            if key not in self._schemas:
                self._schemas[key] = self.writer.register_schema(
                    schema_name, schema_encoding, schema_data().encode())
            channel = self.writer.register_channel(topic, encoding, self._schemas[key])
            self._channels[topic] = channel
        return channel

    def on_message(self, d: Delivery) -> None:
        kind = d.encoding.split(";")[0]
        msg = None
        own = model_for_key(d.key) is not None or (d.schema or "").startswith(f"{PACKAGE}/")
        if (kind == CDR and not own) or (d.key in ROS_KEYS and kind != JSON):
            written = self._record_cdr(d)
        else:
            msg = self._record_own(d)
            written = not self.skips(d.key)
        if self.rerun is not None and written:
            if self.rrd_minutes and time.monotonic() - self._started_rrd > 60 * self.rrd_minutes:
                self.close_rrd()
                return
            try:
                self.log_to_rerun(d, msg)
            except Exception as exc:  # the MCAP has it; the view goes without it
                self.counters[f"not in run.rrd: {type(exc).__name__}"] += 1
                log.debug("%s: not in run.rrd: %s", d.key, exc)

    def close_rrd(self) -> None:
        """Stop writing run.rrd (``rrd_minutes`` are up); run.mcap goes on."""
        assert self.rerun is not None
        self.rerun.close()
        self.rerun = None
        self.counters["run.rrd closed after its minutes"] = 1
        log.info("run.rrd closed after %.0f minutes (rrd_minutes); run.mcap goes on",
                 self.rrd_minutes)

    def log_to_rerun(self, d: Delivery, msg: BaseModel | None) -> None:
        r = self.rerun
        assert r is not None
        if msg is not None:
            method = self._to_rerun.get(type(msg))
            if method is not None:
                getattr(r, method)(msg)
        elif d.key == "tf_static":
            self.tf.update(decode_tf(d.payload))
            with contextlib.suppress(ValueError):  # the arm's mount may come in a later one
                r.mount(self.tf.lookup("world", self.arm.base_link))
        elif d.key == self.points_key:
            cloud = decode_points(d.payload)
            T = self.tf.lookup("world", cloud.frame_id)
            r.cloud(cloud.stamp_ns, cloud.points @ T[:3, :3].T + T[:3, 3])
        elif d.key == OBJECT_POINTS_KEY:
            cloud = decode_points(d.payload)
            r.object_points(cloud.stamp_ns, cloud.points)
        elif d.key == TRUTH_KEY:
            T, _frame, stamp_ns = decode_pose(d.payload)
            r.truth(stamp_ns, T[:3, 3])

    def check_cdr(self, d: Delivery, msgtype: str) -> None:
        """Raise BadMessage unless ``d`` is well-formed CDR of ``msgtype``."""
        parse = {JOINT_TRAJECTORY: parse_joint_trajectory, JOINT_STATE: parse_joint_state}.get(
            msgtype)  # the arm's, a message every frame or more: read by hand, sooner
        if parse is not None:
            try:
                parse(d.payload)
            except ValueError as exc:
                raise BadMessage(f"{d.key}: {exc}") from None
            return
        try:
            self._typestore.deserialize_cdr(d.payload, msgtype)
        except Exception as exc:  # rosbags raises many types on garbage
            raise BadMessage(f"{d.key}: not a valid {msgtype}: {exc}") from None

    def _record_cdr(self, d: Delivery) -> bool:
        """Write a CDR message (a camera cloud as the thinner says, one of a key excluded
        not at all), acknowledging camera frames; returns whether it was written."""
        msgtype, att = cdr_meta(d, ROS_KEYS)
        log_time = att.log_time_ns if att is not None and att.log_time_ns else self.clock.now_ns()
        # Camera clouds as the thinner says (all are acknowledged).
        write = not self.skips(d.key) and (
            d.key != self.points_key or self.thinner.keep(len(d.payload), log_time))
        if d.key == self.points_key and self.thinner.count == SAMPLE and self.thinner.rate_mb_s:
            log.info("camera clouds: %.1f MB a second: writing one in %d (cloud_every, "
                     "cloud_budget_mb_s)", self.thinner.rate_mb_s, self.thinner.every)
        if write:
            self.check_cdr(d, msgtype)
            msgdef = ros2_msgdef(msgtype)
        if write:
            channel = self._channel("/" + d.key, "cdr", msgtype, "ros2msg", lambda: msgdef)
            self.write(channel, log_time, d.payload, log_time, (att.seq if att else 0),
                       on_clock=att is not None and bool(att.log_time_ns))
        if d.key == self.points_key and att is not None:
            self.frames += 1
            self.counters["frames"] = self.frames
            self._flush_if_due()
            self.ack_frame(Header(seq=att.seq, stamp_ns=log_time, trace=[Hop(
                service="source", recv_ns=att.source_ns, sent_ns=att.source_ns)]),
                d.recv_ns, att.seq)
        return write

    def skips(self, key: str) -> bool:
        """Whether ``key`` matches ``record_exclude``."""
        skip = self._skip.get(key)
        if skip is None:
            skip = self._skip[key] = any(e.includes(key) for e in self.excluded)
        return skip

    def _record_own(self, d: Delivery) -> BaseModel | None:
        """Write one of our messages: CDR as a ROS 2 channel (``/`` + key, ``ros2msg``
        schema), JSON (a tool's or an older sender's) as a JSON one (key, ``jsonschema``)."""
        if self.skips(d.key):
            return None

        # A contract key carries its own type: a payload naming another is refused.
        model = model_for_key(d.key) or MESSAGE_TYPES.get((d.schema or "").rpartition("/")[2])
        if model is None:
            raise BadMessage(f"{d.key}: no message type known for this key "
                             f"(encoding {d.encoding!r})")
        msg = decode_model(d, model)
        feed = self._to_summary.get(type(msg))
        if feed is not None:
            feed(msg)
        if isinstance(msg, PlayerStatus) and msg.metadata and not self._wrote_metadata:
            self.writer.add_metadata("wavegrasp.recording", msg.metadata)
            self._wrote_metadata = True
        header = getattr(msg, "header", None)
        if isinstance(msg, Clock):
            self.clock.on_clock(msg)
            self.write_early(msg.header.stamp_ns)
        log_time = msg.header.stamp_ns if isinstance(msg, Clock) else self.clock.now_ns()
        publish_time = header.stamp_ns if header is not None and header.stamp_ns else log_time
        if d.encoding.startswith(CDR):
            msgtype = ros_msgtype(model.__name__)
            channel = self._channel("/" + d.key, "cdr", msgtype, "ros2msg",
                                    lambda: ros2_msgdef(msgtype))
        else:
            channel = self._channel(d.key, "json", model.__name__, "jsonschema",
                                    lambda: schema_text(model.__name__))
        self.write(channel, log_time, d.payload, publish_time, on_clock=isinstance(msg, Clock))
        return msg

    def write(self, channel: int, log_time: int, payload: bytes, publish_time: int,
              sequence: int = 0, on_clock: bool = True) -> None:
        """Write one message; one whose log time is not on the recording's clock
        (``on_clock``) while that clock has not started waits for its first tick, so that a
        run's file stays on one timeline (a viewer's timeline spans the file)."""
        if not on_clock and not self.clock.started and self._early is not None:
            now = time.time_ns()
            self._early.append((channel, payload, publish_time, sequence, now))
            self._early_bytes += len(payload)
            if (now - self._early[0][4] > EARLY_WAIT_NS
                    or self._early_bytes > EARLY_BYTES):
                self.write_early(None)  # no recording clock: at their arrival from now on
            return
        self.writer.add_message(channel, log_time, payload, publish_time,
                                sequence=sequence & 0xFFFFFFFF)
        self.written += 1

    def write_early(self, log_time: int | None) -> None:
        """The messages held for the clock's first tick, logged at ``log_time`` (None: each
        at its arrival, and none held any more)."""
        early, self._early = self._early or [], [] if log_time is not None else None
        self._early_bytes = 0
        for channel, payload, publish_time, sequence, arrived in early:
            self.write(channel, arrived if log_time is None else log_time, payload,
                       publish_time, sequence)

    def _flush_if_due(self) -> None:
        if time.monotonic() - self._last_flush >= self.flush_period_s:
            self.writer.flush()
            self._file.flush()
            self._last_flush = time.monotonic()

    def on_tick(self) -> None:
        self._flush_if_due()

    def on_stop(self) -> None:
        self.write_early(None)  # no clock ever came: at their arrival
        self.writer.add_metadata("wavegrasp.run", {
            "frames": str(self.frames), "messages": str(self.written),
            "bad": json.dumps(dict(self.bus.bad))})
        self.writer.finish()
        self._file.close()
        if self.rerun is not None:
            self.rerun.close()
        log.info("wrote %d messages (%d camera frames) to %s", self.written, self.frames,
                 self.path)
        self.write_summary()

    def write_summary(self) -> None:
        """``summary.json`` beside the run: what the bus said of it (``wavegrasp up`` writes
        its own over it, with exit codes and restarts)."""
        status = self.summary.player_status
        summary = {
            "recording": status.get("recording"), "pace": status.get("pace"),
            "out": str(self.settings.out),
            "ended": "finished" if status.get("state") == "finished" else "stopped",
            "written_by": "recorder", **self.summary.as_dict(),
            "files": sorted(p.name for p in self.settings.out.glob("run*.mcap")),
        }
        path = self.settings.out / "summary.json"
        path.write_text(json.dumps(summary, indent=2) + "\n")
        log.info("%s: grasps %s", path, self.summary.outcome_kinds() or "none")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="wavegrasp recorder", description=__doc__)
    parser.add_argument("--out", type=Path, help="output folder (default: WAVEGRASP_OUT or out)")
    args = parser.parse_args(argv)
    try:
        settings = RecorderSettings.from_env("recorder", out=args.out)
    except ValueError as exc:
        print(f"wavegrasp recorder: {exc}", file=sys.stderr)
        return 2
    setup_logging(settings.log_level)
    try:
        recorder = Recorder(settings)
    except OSError as exc:  # e.g. a folder mounted from the host that this user may not write
        print(f"wavegrasp recorder: cannot write the run to {settings.out}: {exc.strerror} "
              f"(running as uid {os.getuid()}; under docker compose, the folder mounted at "
              "/runs must be writable by WAVEGRASP_UID)", file=sys.stderr)
        return 2
    return recorder.run()

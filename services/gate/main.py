"""``wavegrasp gate``: one ``wavegrasp/gate/decision`` (go / no-go and why) for every plan.

Subscribes ``wavegrasp/perception/object`` and ``wavegrasp/predictor/prediction`` (to score the
predictions, the paper's eq. 13-14), ``wavegrasp/planner/plan`` (to decide) and
``wavegrasp/sim/outcome`` (an outcome ends the plan's execution). In closed-loop execution it
also decides on the planner's updates of the executing plan and, at every camera frame until
the grasp time, watches it: past its limits (:meth:`Gate.watch`) it sends
``wavegrasp/gate/abort`` and the arm retreats. Each decision carries the
plan's header plus the gate's hop, so its trace shows the whole chain from the camera frame.
It also commands the arm (:mod:`wavegrasp.gate.command`), in the types ros2_control's
controllers take: every approved plan, update and abort, and the planner's standby moves of
the idle arm (``wavegrasp/planner/standby``), as ``trajectory_msgs/msg/JointTrajectory`` for
the arm's joint trajectory controller and for the jaw's (:class:`ArmTopics`), each sent right
after the decision it carries out (before the abort). While time runs as the wall's it sends a
heartbeat (``wavegrasp/gate/heartbeat``) every ``heartbeat_s``: the arm stops and holds when
they stop coming (the sim's ``watchdog_s``).
Thresholds come from ``WAVEGRASP_<FIELD>`` for each field of :class:`GateConfig` and
:class:`CommandConfig`.
"""

from __future__ import annotations

import argparse
import logging
import sys
import time

from wavegrasp.arm import ArmModel
from wavegrasp.arm.motion import Attempt, JointPath
from wavegrasp.gate.command import CommandConfig, Commander
from wavegrasp.gate.decision import Gate, GateConfig
from wavegrasp.recording_io.ros_msgs import JOINT_TRAJECTORY, encode_joint_trajectory
from wavegrasp.runtime.bus import Bus, Delivery
from wavegrasp.runtime.service import Service, setup_logging
from wavegrasp.runtime.settings import ArmTopics, Settings
from wavegrasp.runtime.trace import derived_header, new_header
from wavegrasp.schemas import (
    HEARTBEAT_KEY,
    ArmStandby,
    GateAbort,
    GateDecision,
    GraspOutcome,
    GraspPlan,
    Heartbeat,
    MotionPrediction,
    ObjectObservation,
)

log = logging.getLogger("wavegrasp.gate")
DECISION_KEY = "wavegrasp/gate/decision"
ABORT_KEY = "wavegrasp/gate/abort"


class GateSettings(Settings, GateConfig, CommandConfig, ArmTopics):
    """Bus settings plus every :class:`GateConfig` and :class:`CommandConfig` field (env
    ``WAVEGRASP_EPSILON_M``, ``WAVEGRASP_HOLD_S``...) and the arm's topics."""

    def gate_config(self) -> GateConfig:
        return GateConfig(**self.model_dump(include=set(GateConfig.model_fields)))

    def command_config(self) -> CommandConfig:
        return CommandConfig(**self.model_dump(include=set(CommandConfig.model_fields)))


def plan_latency_s(plan: GraspPlan, now_wall_ns: int) -> float:
    """Wall seconds since the plan's data entered the pipeline (its first hop's receipt); 0
    without a trace, and never negative (clocks of different hosts may disagree)."""
    if not plan.header.trace:
        return 0.0
    return max(0.0, (now_wall_ns - plan.header.trace[0].recv_ns) / 1e9)


class GateService(Service):
    ack_after = "planner"

    def __init__(self, settings: GateSettings, bus: Bus | None = None) -> None:
        arm = ArmModel.load(settings.arm_urdf or None)  # before the bus: fail cleanly
        super().__init__(settings, bus)
        self.cfg = settings
        self.gate = Gate(settings.gate_config())
        self.commander = Commander(arm, settings.command_config())
        self._standby: JointPath | None = None  # asked for this frame
        self._beat_at, self._beats = float("-inf"), 0  # the last heartbeat (monotonic s)
        self.bus.watch_alive()
        self.bus.mark_urgent(DECISION_KEY, ABORT_KEY, HEARTBEAT_KEY, settings.arm_trajectory_key,
                             settings.jaw_trajectory_key)
        self.bus.subscribe("wavegrasp/perception/object", self.on_observation, ObjectObservation)
        self.bus.subscribe("wavegrasp/predictor/prediction", self.on_prediction, MotionPrediction)
        self.bus.subscribe("wavegrasp/planner/plan", self.on_plan, GraspPlan)
        self.bus.subscribe("wavegrasp/sim/outcome", self.on_outcome, GraspOutcome)
        self.bus.subscribe("wavegrasp/planner/standby", self.on_standby, ArmStandby)

    def on_observation(self, msg: ObjectObservation, _d: Delivery) -> None:
        if self.gate.on_observation(msg) is not None:
            self.counters["errors scored"] += 1

    def on_prediction(self, msg: MotionPrediction, _d: Delivery) -> None:
        self.gate.on_prediction(msg)

    def on_outcome(self, msg: GraspOutcome, _d: Delivery) -> None:
        self.counters["outcomes"] += 1
        self.gate.on_outcome(msg.plan_id)

    def on_standby(self, msg: ArmStandby, _d: Delivery) -> None:
        """Checked now (a bad one is counted on its key), commanded at the frame's end: a go
        in the same frame comes first."""
        names, s = list(msg.joint_names), msg.joint_trajectory
        if names != self.commander.names:
            raise ValueError(f"standby joint_names {names} are not the arm's "
                             f"{self.commander.names}")
        n = len(names)
        if len(s) < 2 or any(len(x.positions) != n or len(x.velocities) not in (0, n)
                             for x in s):
            raise ValueError(f"standby joint_trajectory needs 2 or more samples, each of {n} "
                             f"positions (and velocities, if any)")
        self._standby = JointPath(names, [x.t_ns * 1e-9 for x in s], [x.positions for x in s],
                                  [x.velocities or [0.0] * len(names) for x in s])

    def finish_frame(self, frame_seq: int) -> None:
        self.watch()
        self.command_standby()

    def command_standby(self) -> None:
        move, self._standby = self._standby, None
        if move is None:
            return
        path = self.commander.standby(move, self.clock.now_ns() * 1e-9)
        if path is None:
            self.counters["standby moves ignored: busy"] += 1
            return
        self.counters["standby moves"] += 1
        self.send(path)

    def send(self, arm: JointPath | None, jaw: JointPath | None = None) -> None:
        """The arm's and the jaw's new paths to their controllers."""
        for path, key in ((arm, self.cfg.arm_trajectory_key), (jaw, self.cfg.jaw_trajectory_key)):
            if path is not None:
                self.bus.publish_cdr(key, encode_joint_trajectory(
                    path.names, path.times, path.q, path.qd), JOINT_TRAJECTORY)

    def on_tick(self) -> None:
        if self.settings.clock == "wall":  # a live vehicle's inputs may go silent between
            self.watch()                   # frames; a replay's are judged at each frame
        self.beat()

    def beat(self) -> None:
        """The heartbeat the arm's watchdog waits for, every ``heartbeat_s`` of wall time
        while time runs as the wall's (live, or a replay in real time); none in a lockstep or
        fast replay, whose frames wait for the pipeline however long it takes."""
        now = time.monotonic()
        if self.clock.rate <= 0 or now - self._beat_at < self.cfg.heartbeat_s:
            return
        self._beat_at = now
        self.bus.publish(HEARTBEAT_KEY, Heartbeat(
            header=new_header(self.name, self._beats, self.clock.now_ns()),
            period_s=self.cfg.heartbeat_s))
        self._beats += 1

    def watch(self) -> None:
        found = self.gate.watch(self.clock.now_ns())
        if found is None:
            return
        plan_id, kind, reason, value, limit = found
        self.gate.on_outcome(plan_id)  # aborted: no longer executing, no more updates
        self.counters["aborts"] += 1
        self.counters[f"abort: {kind}"] += 1
        log.info("abort %s: %s", plan_id, reason)
        paths = self.commander.abort(self.clock.now_ns() * 1e-9)
        if paths is not None:
            self.send(*paths)
        self.bus.publish(ABORT_KEY, GateAbort(
            header=new_header(self.name, 0, self.clock.now_ns()), plan_id=plan_id,
            reason=reason, value=value, limit=limit))

    def on_plan(self, msg: GraspPlan, d: Delivery) -> None:
        alive = self.bus.alive_now()
        header = derived_header(msg.header, self.name, d.recv_ns)
        now_ns = self.clock.now_ns()
        # In recording time: a lockstep replay waits for the pipeline, so its latency costs
        # the plan nothing (and a wall-clock figure would make runs differ).
        latency_s = plan_latency_s(msg, time.time_ns()) * self.clock.rate
        try:
            decision = self.gate.decide(msg, now_ns, alive, latency_s, header=header)
            if decision.go:
                try:  # what the arm is to follow
                    attempt = Attempt.from_message(msg, self.commander.names)
                except ValueError:
                    if msg.update_of is None:
                        self.gate.on_outcome(msg.plan_id)  # not executing after all
                    raise
        except ValueError as exc:  # a plan we cannot judge is a plan we do not run
            cfg = self.gate.config
            decision = GateDecision(
                header=header, plan_id=msg.plan_id, go=False,
                mean_error_m=self.gate.mean_error(now_ns), threshold_m=cfg.epsilon_m,
                window_s=cfg.window_s, reason=f"bad plan: {exc}", failed=["bad plan"])
        failed = getattr(decision, "failed", [])
        self.counters["go" if decision.go else "no-go"] += 1
        for name in dict.fromkeys(failed):
            self.counters[f"no-go: {name}"] += 1
        if not decision.go:
            log.info("no-go %s: %s", msg.plan_id, decision.reason)
        self.bus.publish(DECISION_KEY, decision)
        if decision.go:  # its paths right after it (they start later: t_start is ahead)
            self.send(*self.commander.grasp(attempt, update=msg.update_of is not None,
                                            now_s=now_ns * 1e-9))


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="wavegrasp gate", description=__doc__)
    parser.add_argument("--epsilon-m", type=float, help="ε, metres (default: "
                        "WAVEGRASP_EPSILON_M or 0.010)")
    parser.add_argument("--window-s", type=float, help="Δt_w, seconds (default: "
                        "WAVEGRASP_WINDOW_S or 2.0)")
    args = parser.parse_args(argv)
    try:
        settings = GateSettings.from_env("gate", epsilon_m=args.epsilon_m,
                                         window_s=args.window_s)
    except ValueError as exc:
        print(f"wavegrasp gate: {exc}", file=sys.stderr)
        return 2
    setup_logging(settings.log_level)
    return GateService(settings).run()

"""``wavegrasp gate``: one ``wavegrasp/gate/decision`` (go / no-go and why) for every plan.

Subscribes ``wavegrasp/perception/object`` and ``wavegrasp/predictor/prediction`` (to score the
predictions, the paper's eq. 13-14), ``wavegrasp/planner/plan`` (to decide) and
``wavegrasp/sim/outcome`` (an outcome ends the plan's execution). In closed-loop execution it
also decides on the planner's updates of the executing plan and, at every camera frame until
the grasp time, watches it: past its limits (:meth:`Gate.watch`) it sends
``wavegrasp/gate/abort`` and the arm retreats. Each decision carries the
plan's header plus the gate's hop, so its trace shows the whole chain from the camera frame.
Thresholds come from ``WAVEGRASP_<FIELD>`` for each field of :class:`GateConfig`.
"""

from __future__ import annotations

import argparse
import logging
import sys
import time

from wavegrasp.gate.decision import Gate, GateConfig
from wavegrasp.runtime.bus import Bus, Delivery
from wavegrasp.runtime.service import Service, setup_logging
from wavegrasp.runtime.settings import Settings
from wavegrasp.runtime.trace import derived_header, new_header
from wavegrasp.schemas import (
    GateAbort,
    GateDecision,
    GraspOutcome,
    GraspPlan,
    MotionPrediction,
    ObjectObservation,
)

log = logging.getLogger("wavegrasp.gate")
DECISION_KEY = "wavegrasp/gate/decision"
ABORT_KEY = "wavegrasp/gate/abort"


class GateSettings(Settings, GateConfig):
    """Bus settings plus every :class:`GateConfig` field (env ``WAVEGRASP_EPSILON_M``...)."""

    def gate_config(self) -> GateConfig:
        return GateConfig(**self.model_dump(include=set(GateConfig.model_fields)))


def plan_latency_s(plan: GraspPlan, now_wall_ns: int) -> float:
    """Wall seconds since the plan's data entered the pipeline (its first hop's receipt); 0
    without a trace, and never negative (clocks of different hosts may disagree)."""
    if not plan.header.trace:
        return 0.0
    return max(0.0, (now_wall_ns - plan.header.trace[0].recv_ns) / 1e9)


class GateService(Service):
    ack_after = "planner"

    def __init__(self, settings: GateSettings, bus: Bus | None = None) -> None:
        super().__init__(settings, bus)
        self.gate = Gate(settings.gate_config())
        self.bus.watch_alive()
        self.bus.subscribe("wavegrasp/perception/object", self.on_observation, ObjectObservation)
        self.bus.subscribe("wavegrasp/predictor/prediction", self.on_prediction, MotionPrediction)
        self.bus.subscribe("wavegrasp/planner/plan", self.on_plan, GraspPlan)
        self.bus.subscribe("wavegrasp/sim/outcome", self.on_outcome, GraspOutcome)

    def on_observation(self, msg: ObjectObservation, _d: Delivery) -> None:
        if self.gate.on_observation(msg) is not None:
            self.counters["errors scored"] += 1

    def on_prediction(self, msg: MotionPrediction, _d: Delivery) -> None:
        self.gate.on_prediction(msg)

    def on_outcome(self, msg: GraspOutcome, _d: Delivery) -> None:
        self.counters["outcomes"] += 1
        self.gate.on_outcome(msg.plan_id)

    def finish_frame(self, frame_seq: int) -> None:
        self.watch()

    def on_tick(self) -> None:
        if self.settings.clock == "wall":  # a live vehicle's inputs may go silent between
            self.watch()                   # frames; a replay's are judged at each frame

    def watch(self) -> None:
        found = self.gate.watch(self.clock.now_ns())
        if found is None:
            return
        plan_id, kind, reason, value, limit = found
        self.gate.on_outcome(plan_id)  # aborted: no longer executing, no more updates
        self.counters["aborts"] += 1
        self.counters[f"abort: {kind}"] += 1
        log.info("abort %s: %s", plan_id, reason)
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

"""The planner again on a run's own messages: ``wavegrasp replan RUN...``.

Drives a planner service of today's code and settings with what the planner of a recorded
run received (the camera's transforms, perception's observations, the arm's states, the
gate's decisions, the outcomes and the predictions), in the order the recorder logged them,
and counts what it makes of the predictions: how many it planned on, how many plans, how
many with none and why. The arm, the gate and the outcomes stay the run's: the arm is idle
where it was idle in the run, so the counts compare planners prediction by prediction, not
whole runs (a plan made now that was not made then is never executed). It answers "what would
this change to the planner have done on these runs?" without generating the recordings or
running the pipeline again. RUN: a run's directory (its run.mcap) or the run.mcap itself;
``--each`` prints every prediction the planner planned on (seconds from the run's first
message) and whether it planned.
"""

from __future__ import annotations

import argparse
from collections import Counter
from pathlib import Path

from wavegrasp.gate.main import DECISION_KEY
from wavegrasp.ops.bench_zenoh_hop import start_router, stop
from wavegrasp.perception.main import OBJECT_KEY
from wavegrasp.planner.main import PlannerService, PlannerSettings
from wavegrasp.predictor.main import PREDICTION_KEY
from wavegrasp.recording_io.mcap_read import read_mcap
from wavegrasp.recording_io.own_messages import decode_own, own_topics
from wavegrasp.recording_io.ros_msgs import decode_tf
from wavegrasp.runtime.bus import Delivery
from wavegrasp.sim.main import OUTCOME_KEY

TF_STATIC_TOPIC = "/tf_static"
#: What the planner counts for each prediction it planned on.
OUTCOMES = ("plans", "no plan")


def run_mcap(run: Path) -> Path:
    """``run`` itself or the run.mcap in it; a clear error where there is none."""
    path = run / "run.mcap" if run.is_dir() else run
    if not path.is_file():
        raise SystemExit(f"replan: {path}: no such run.mcap")
    return path


def replan(path: Path, endpoint: str, each: bool = False) -> Counter:
    """The planner's counters over the run in ``path`` (a run.mcap), replayed."""
    # Replayed as fast as it goes: every prediction planned on as it comes, as in lockstep.
    service = PlannerService(PlannerSettings.from_env(
        "planner", env={"ZENOH_CONNECT": endpoint, "WAVEGRASP_PACE": "lockstep"}))
    handlers = {OBJECT_KEY: service.on_observation, DECISION_KEY: service.on_decision,
                OUTCOME_KEY: service.on_outcome, PREDICTION_KEY: service.on_prediction}
    # The arm's own topics, in ROS 2 types: the planner decodes them itself.
    arm = {service.cfg.joint_states_key: service.on_joint_states,
           service.cfg.arm_trajectory_key: service.on_arm_trajectory}
    t0: int | None = None
    try:
        topics = [*own_topics(handlers), TF_STATIC_TOPIC, *(f"/{key}" for key in arm)]
        for schema, channel, message in read_mcap(path, topics):
            t0 = message.log_time if t0 is None else t0
            if channel.topic == TF_STATIC_TOPIC:
                service.tf.update(decode_tf(message.data))
                continue
            key = channel.topic.lstrip("/")
            delivery = Delivery(key, message.data, "", None, message.log_time, 0)
            if key in arm:
                try:
                    arm[key](delivery)
                except ValueError as exc:
                    service.bus.count_bad(key, str(exc)[:300])
                continue
            handle = handlers[key]
            try:
                msg = decode_own(schema, channel, message)
                if msg is None:
                    raise ValueError(f"{channel.topic}: not one of our messages")
            except ValueError as exc:
                service.bus.count_bad(key, str(exc)[:300])
                continue
            try:
                handle(msg, delivery)
            except ValueError as exc:  # as the service's own subscriptions count it
                service.bus.count_bad(key, str(exc)[:300])
                continue
            if key != PREDICTION_KEY:
                continue
            before = Counter({k: service.counters[k] for k in OUTCOMES})
            service.on_tick()
            if each and (done := [k for k in OUTCOMES if service.counters[k] > before[k]]):
                print(f"  {(message.log_time - t0) * 1e-9:7.2f} s  prediction "
                      f"{msg.header.seq}: {done[0]}")
        return Counter(service.counters)
    finally:
        service.bus.close()


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("runs", nargs="+", type=Path, help="run directories or run.mcap files")
    p.add_argument("--each", action="store_true", help="print every prediction planned on")
    a = p.parse_args(argv)
    paths = [run_mcap(r) for r in a.runs]
    router, endpoint = start_router()
    try:
        print("| run | planned on | plans | no plan | plan rate | top rejections |")
        print("|---|---|---|---|---|---|")
        for path in paths:
            c = replan(path, endpoint, a.each)
            on = c["plans"] + c["no plan"]
            top = ", ".join([f"{k.removeprefix('rejected: ')} {n}" for k, n in c.most_common()
                            if k.startswith("rejected: ")][:3])
            name = path.parent.name if path.name == "run.mcap" else path.name
            print(f"| {name} | {on} | {c['plans']} | {c['no plan']} | "
                  f"{c['plans'] / max(on, 1):.0%} | {top} |", flush=True)
    finally:
        stop(router)


if __name__ == "__main__":
    main()

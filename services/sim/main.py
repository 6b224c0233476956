"""``wavegrasp sim``: PyBullet stands in for the arm and the world, on the recording's clock.

The arm (ours, or ``WAVEGRASP_ARM_URDF``) stands on its mount from ``tf_static``; the object,
the recording's own where its metadata holds its scenario (a generated recording: the sim
stands in for the world), else a sphere or a cylinder of the size perception reports until
perception's mesh arrives (applied between attempts), on its tether to the seabed, follows
``groundtruth/object`` (or, in a recording without ground truth, the tracked centroid)
through a bounded-force drive.
The arm is driven the way ros2_control drives one, and only so: it follows the
``trajectory_msgs/msg/JointTrajectory`` sent to its joint trajectory controller and to its
jaw's (:class:`~wavegrasp.runtime.settings.ArmTopics`; the gate commands them), each taking
effect at the end of the camera frame it came in, and publishes its joints and fingers as
``sensor_msgs/msg/JointState`` on ``joint_states`` once a camera frame; a real arm behind
zenoh-bridge-ros2dds takes its place unchanged.
The judge beside it reads what an observer of the tank would: a ``go`` from the gate starts an
attempt of the approved plan, judged physically (:mod:`wavegrasp.sim.executor`) and published
on ``wavegrasp/sim/outcome`` with the next camera frame's acknowledgement; the pipeline tries
again, up to ``attempts`` per trial. ``wavegrasp/sim/arm_state`` (the joints and the attempt
judged) is published once a camera frame too.
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
import time
from pathlib import Path

import numpy as np
from pydantic import Field
from scipy.spatial.transform import Rotation

from wavegrasp.arm import ArmModel
from wavegrasp.arm.motion import JointPath
from wavegrasp.recording_io.ros_msgs import (
    JOINT_STATE,
    StaticTransforms,
    decode_joint_trajectory,
    decode_pose_quaternion,
    decode_tf,
    encode_joint_state,
)
from wavegrasp.runtime.bus import Bus, Delivery
from wavegrasp.runtime.service import Service, setup_logging
from wavegrasp.runtime.settings import ArmTopics, Settings
from wavegrasp.runtime.state import StateFile
from wavegrasp.runtime.trace import CdrAttachment, new_header
from wavegrasp.schemas import (
    HEARTBEAT_KEY,
    ArmState,
    FrameAck,
    GateAbort,
    GateDecision,
    GraspOutcome,
    GraspPlan,
    Heartbeat,
    MotionPrediction,
    ObjectMesh,
    ObjectObservation,
    PlayerStatus,
)
from wavegrasp.schemas.mesh_codec import decode_mesh
from wavegrasp.sim.executor import Attempt, Executor, Result
from wavegrasp.sim.watchdog import Watchdog
from wavegrasp.sim.world import STEP_S, ObjectShape, SimWorld
from wavegrasp.wavetank.scenario import ObjectModel

log = logging.getLogger("wavegrasp.sim")
OUTCOME_KEY = "wavegrasp/sim/outcome"
TRUTH_KEY = "groundtruth/object"
ARM_STATE_KEY = "wavegrasp/sim/arm_state"
#: Without ground truth for this long (recording seconds), the tracked centroid drives.
TRUTH_STALE_S = 0.5
#: A pose stamped further ahead of the recording clock is refused: the scene would jump there
#: and then ignore every later pose as older.
MAX_AHEAD_S = 1.0
#: How long (wall s) an approval waits for its plan, which comes from another publisher and may
#: arrive after it, before it is dropped as a decision for a plan that never came.
PLAN_WAIT_S = 2.0


class SimSettings(Settings, ArmTopics):
    gui: bool = False
    trials: int = Field(1, ge=1, description="trials in this run, one after the other")
    attempts: int = Field(3, ge=1, description="attempts a trial at most")
    trial_timeout_s: float = Field(10.0, gt=0, description="a trial with no plan approved "
                                   "this long (recording seconds) after it began or after "
                                   "its last attempt ends as a failure")
    drive_force_n: float = 5.0
    tether: bool = Field(True, description="a tether from the object's lower end to the "
                         "seabed, which the arm must not touch")
    stop_after_trials: bool = Field(False, description="exit once the last trial has ended "
                                    "(compose labels the sim as ending the run)")
    resume_file: Path | None = Field(None, description="where the sim notes its trial and "
                                     "attempt; restarted after a crash, it goes on from there")
    watchdog_s: float = Field(0.5, gt=0, description="wall seconds without the gate's "
                              "heartbeat, while time runs as the wall's, before the arm stops "
                              "and holds (and refuses new paths until the next heartbeat)")
    freshness_s: float = Field(1.0, gt=0, description="a path that starts longer ago than "
                               "this (recording seconds) is refused: an approval delayed on "
                               "the way (a link that came back) is not carried out")


class SimService(Service):
    ack_after = "gate"

    def __init__(self, settings: SimSettings, bus: Bus | None = None) -> None:
        self.arm = ArmModel.load(settings.arm_urdf or None)  # before the bus: fail cleanly
        super().__init__(settings, bus)
        self.cfg = settings
        self.tf = StaticTransforms()
        self.shape: ObjectShape | None = None
        self._truth_shape = False  # the shape is the recording's own object
        self.world: SimWorld | None = None
        self.executor: Executor | None = None
        self.plans: dict[str, GraspPlan] = {}
        self.predictions: dict[int, tuple[np.ndarray, np.ndarray]] = {}
        self.trial = 0  # the trial under way, from 0
        self.attempt = 0  # attempts made in it
        self._idle_since: float | None = None  # recording s: trial began or attempt ended
        self._truth_at = -np.inf
        self._executing: str | None = None
        self._pose: tuple[float, np.ndarray, np.ndarray] | None = None  # the newest, to build
        self._results: list[Result] = []
        self._mesh: np.ndarray | None = None  # vertices of a mesh not in the scene yet
        self._truths = 0  # ground truths received (their attachments' sequence + 1)
        self._go: Attempt | None = None  # approved this frame, not started yet
        self._splice: tuple[str, Attempt] | None = None  # an update approved this frame
        self._abort: GateAbort | None = None  # the gate's abort this frame
        self._paths: list[JointPath] = []  # sent to the arm's controllers this frame
        self._go_waiting: tuple[str, float] | None = None  # approved: (plan id, monotonic s)
        self._plans_flow = False  # a warm prediction or a decision has come: trials begin
        self._held: list[tuple[int, FrameAck, Delivery]] = []  # (truths needed, ack, delivery)
        self.watchdog = Watchdog(settings.watchdog_s)
        self.bus.mark_urgent(settings.joint_states_key)  # the arm's state, ahead of clouds
        self.state = StateFile(settings.resume_file)
        self._saved: dict | None = None
        self.resume(self.state.load())
        self.bus.subscribe("tf_static", lambda d: self.tf.update(decode_tf(d.payload)))
        self.bus.subscribe(TRUTH_KEY, self.on_truth)
        self.bus.subscribe("wavegrasp/perception/object", self.on_observation, ObjectObservation)
        self.bus.subscribe("wavegrasp/perception/mesh", self.on_mesh, ObjectMesh)
        self.bus.subscribe("wavegrasp/predictor/prediction", self.on_prediction,
                           MotionPrediction)
        self.bus.subscribe("wavegrasp/planner/plan", self.on_plan, GraspPlan)
        self.bus.subscribe(settings.arm_trajectory_key, self.on_trajectory)
        self.bus.subscribe(settings.jaw_trajectory_key, self.on_trajectory)
        self.bus.subscribe("wavegrasp/gate/decision", self.on_decision, GateDecision)
        self.bus.subscribe("wavegrasp/gate/abort", self.on_abort, GateAbort)
        self.bus.subscribe("wavegrasp/player/status", self.on_player_status, PlayerStatus)
        self.bus.subscribe(HEARTBEAT_KEY, self.on_heartbeat, Heartbeat)

    def resume(self, state: dict | None) -> None:
        """Go on with the trials of a sim that crashed; an attempt it was executing failed."""
        if state is None:
            return
        try:
            self.trial, self.attempt = int(state["trial"]), int(state["attempt"])
            self._plans_flow = bool(state["plans_flow"])
            executing = state["executing"]
        except (KeyError, TypeError, ValueError) as exc:
            log.warning("%s: not a sim state (%s); starting afresh", self.state.path, exc)
            return
        log.warning("resuming at trial %d after %d attempts", self.trial, self.attempt)
        if executing:
            self.counters["attempts cut short by a restart"] += 1
            self._results.append(Result(str(executing), False, "other", {
                "reason": "the sim restarted during this attempt"}))

    def note_state(self) -> None:
        state = {"trial": self.trial, "attempt": self.attempt, "executing": self._executing,
                 "plans_flow": self._plans_flow}
        if state != self._saved:
            self.state.save(state)
            self._saved = state

    # --- inputs -------------------------------------------------------------------------

    def check_not_ahead(self, stamp_ns: int) -> None:
        ahead_s = (stamp_ns - self.clock.now_ns()) / 1e9
        if ahead_s > MAX_AHEAD_S:
            raise ValueError(f"stamp {stamp_ns} is {ahead_s:.1f} s ahead of the recording clock")

    def on_truth(self, d: Delivery) -> None:
        position, quat, stamp_ns = decode_pose_quaternion(d.payload)
        self.check_not_ahead(stamp_ns)
        att = CdrAttachment.decode(d.attachment)
        if att is not None:
            self._truths = max(self._truths, att.seq + 1)
        self._truth_at = stamp_ns * 1e-9
        self.advance(stamp_ns * 1e-9, position, quat)
        self.release_frames()

    def on_upstream_ack(self, msg: FrameAck, d: Delivery) -> None:
        """Finish a frame once every ground truth the player sent before it, and the plan of
        an approval that came in it, have arrived: they come from other publishers than the
        acknowledgement (the player, the planner), so they may come after it, and a lockstep
        run must see them alike every time."""
        needed = self.clock.published.get(TRUTH_KEY, 0)
        if self._held or self._truths < needed or self._go_waiting is not None:
            self.counters["frames waiting for ground truth" if self._truths < needed
                          else "frames waiting for a plan"] += 1
            self._held.append((needed, msg, d))
            return
        super().on_upstream_ack(msg, d)

    def release_frames(self) -> None:
        """Finish the held frames whose ground truths and approved plan are here now."""
        while self._held and self._truths >= self._held[0][0] and self._go_waiting is None:
            _needed, msg, delivery = self._held.pop(0)
            super().on_upstream_ack(msg, delivery)

    def on_tick(self) -> None:
        if self._go_waiting is not None and (
                time.monotonic() - self._go_waiting[1] > PLAN_WAIT_S):
            self.drop_waiting_go()
            self.release_frames()
        # Only while time runs as the wall's: a lockstep or fast replay beats no time.
        if self.clock.rate > 0 and self.watchdog.silent(time.monotonic()):
            self.drain()  # heartbeats queued behind a long frame are no silence
            if not self.watchdog.check(time.monotonic()):
                return
            self.counters["watchdog: stopped, no heartbeat"] += 1
            assert self.watchdog.last is not None
            self.counters["watchdog: the last stop, ms after the last heartbeat"] = int(
                (time.monotonic() - self.watchdog.last) * 1e3)
            log.warning("no heartbeat from the gate for %.1f s: the arm stops and holds",
                        self.watchdog.timeout_s)
            self._paths.clear()
            if self.executor is not None:
                self.executor.hold()
                if self.executor.attempt is not None:  # its plan assumed an arm that went on
                    self.publish_outcome(self.executor.abort(
                        f"no heartbeat from the gate for {self.watchdog.timeout_s:.1f} s: "
                        "the arm held"))

    def on_heartbeat(self, _msg: Heartbeat, _d: Delivery) -> None:
        if self.watchdog.beat(time.monotonic()):
            log.info("the gate's heartbeat is back: the arm takes paths again")

    def on_player_status(self, msg: PlayerStatus, _d: Delivery) -> None:
        """The world's own object, from a generated recording's scenario (the sim stands in
        for the world; nothing upstream of it sees this)."""
        if self._truth_shape or self.world is not None or "scenario" not in msg.metadata:
            return
        try:
            obj = ObjectModel(**json.loads(msg.metadata["scenario"])["object"])
        except (ValueError, KeyError, TypeError) as exc:
            raise ValueError(f"metadata.scenario.object: {exc}") from None
        spec = obj.spec()
        # A sphere or cylinder is PyBullet's own (exact, and quicker to collide); another
        # shape, its mesh's hull. A copy: a view would keep open3d's buffer alive to the end,
        # and open3d then ends the process with exit code 1 over the "leak".
        vertices = None
        if spec.shape not in ("sphere", "cylinder"):
            # Here, not at the top: open3d's import is half the sim's start (1 s of 2.1 s
            # measured), and a killed sim is back sooner without it (`wavegrasp faults`).
            from wavegrasp.wavetank.camera import object_mesh

            vertices = np.array(object_mesh(spec).vertex.positions.numpy(), dtype=float)
        self.shape = ObjectShape(spec.shape, spec.radius, spec.length, vertices=vertices,
                                 tether_m=spec.attach_offset)
        self._truth_shape = True

    def on_observation(self, msg: ObjectObservation, _d: Delivery) -> None:
        if self.shape is None and msg.radius_m is not None and msg.shape is not None:
            length = msg.length_m or 2 * msg.radius_m
            self.shape = ObjectShape(msg.shape, msg.radius_m, length)
        c, t = msg.centroid, msg.header.stamp_ns * 1e-9
        if c is not None and t - self._truth_at > TRUTH_STALE_S:
            self.check_not_ahead(msg.header.stamp_ns)
            axis = np.array([0.0, 0.0, 1.0]) if msg.axis is None else np.array(
                [msg.axis.x, msg.axis.y, msg.axis.z])
            quat = Rotation.align_vectors([axis], [[0.0, 0.0, 1.0]])[0].as_quat()
            self.advance(t, np.array([c.x, c.y, c.z]), quat)

    def on_mesh(self, msg: ObjectMesh, _d: Delivery) -> None:
        """Kept until the arm is idle: the object is not reshaped under the gripper."""
        vertices, _triangles = decode_mesh(msg.model_dump())
        if len(vertices) < 4:
            raise ValueError(f"mesh of {len(vertices)} vertices: a closed mesh needs 4")
        if not self._truth_shape:  # the world's own object is not reshaped by a view of it
            self._mesh = vertices

    def on_prediction(self, msg: MotionPrediction, _d: Delivery) -> None:
        """Kept a while: an attempt is judged against the prediction its plan came from. The
        first warm one begins trial 0: from then on the planner may plan, and a predictor
        too unsure for it to plan on must fail its trials, not leave them unbegun."""
        self._plans_flow = self._plans_flow or msg.warm
        if len(msg.samples) >= 2:
            self.predictions[msg.header.seq] = (
                np.array([x.t_ns for x in msg.samples]) * 1e-9,
                np.array([[x.x, x.y, x.z] for x in msg.samples]))
        while len(self.predictions) > 50:
            self.predictions.pop(next(iter(self.predictions)))

    def on_plan(self, msg: GraspPlan, _d: Delivery) -> None:
        self.plans[msg.plan_id] = msg
        while len(self.plans) > 20:
            self.plans.pop(next(iter(self.plans)))
        if self._go_waiting is not None and self._go_waiting[0] == msg.plan_id:
            self._go_waiting = None
            self.approve(msg)
            self.release_frames()

    def on_trajectory(self, d: Delivery) -> None:
        """A path for the arm's or the jaw's controller, followed from the frame's end (so
        whichever moment of the frame it comes in, the arm moves alike). Its joints may come
        in any order; they must be all of the arm's, or all of the jaw's."""
        names, times, q, qd = decode_joint_trajectory(d.payload)
        if self.watchdog.tripped:
            self.counters["paths refused: no heartbeat"] += 1
            return
        if self.world is not None and times[0] < self.world.time_s - self.cfg.freshness_s:
            self.counters["paths refused: stale"] += 1
            log.warning("a path starting %.1f s ago refused (freshness %.1f s)",
                        self.world.time_s - times[0], self.cfg.freshness_s)
            return
        for own in (list(self.arm.joint_names), list(self.arm.jaw_joints)):
            if sorted(names) == sorted(own):
                order = [names.index(n) for n in own]
                self._paths.append(JointPath(own, times, q[:, order], qd[:, order]))
                return
        raise ValueError(f"joint_names {names} are neither the arm's "
                         f"{list(self.arm.joint_names)} nor the jaw's {list(self.arm.jaw_joints)}")

    def follow_paths(self) -> None:
        paths, self._paths = self._paths, []
        for path in paths:
            if self.executor is None:
                self.counters["paths ignored: no scene yet"] += 1
                continue
            self.executor.follow(path)
            self.counters["paths followed"] += 1

    def on_decision(self, msg: GateDecision, _d: Delivery) -> None:
        self._plans_flow = True  # trial 0 begins at this frame's end
        if not msg.go:
            return
        if self._go is not None:
            self.counters["ignored: another go this frame"] += 1
            return
        if self._go_waiting is not None:  # the gate approves one plan at a time: that one's
            self.drop_waiting_go()        # plan is not coming
        plan = self.plans.get(msg.plan_id)
        if plan is None:  # the planner's message may come after the gate's: wait for it
            self._go_waiting = (msg.plan_id, time.monotonic())
            return
        self.approve(plan)

    def drop_waiting_go(self) -> None:
        assert self._go_waiting is not None
        plan_id, _since = self._go_waiting
        self._go_waiting = None
        self.bus.count_bad("wavegrasp/gate/decision",
                           f"decision for plan {plan_id} that never arrived")

    def approve(self, plan: GraspPlan) -> None:
        """Judge an approved plan, or an update of the one judged, from the end of the frame
        (below)."""
        attempt = Attempt.from_message(plan, self.arm.joint_names)
        attempt.predicted = self.predictions.get(plan.header.seq)
        if plan.update_of is not None:
            self._splice = (plan.update_of, attempt)
            return
        self._go = attempt  # started when the frame finishes (below)

    def on_abort(self, msg: GateAbort, _d: Delivery) -> None:
        """Kept for the frame's end, like an approval."""
        self._abort = msg

    def apply_abort_and_update(self) -> None:
        """At the frame's end: the gate's abort of the attempt judged (it ends, aborted; the
        arm backs out as commanded), else an approved update of it (judged by it from now)."""
        abort, self._abort = self._abort, None
        splice, self._splice = self._splice, None
        attempt = self.executor.attempt if self.executor is not None else None
        if abort is not None:
            if attempt is not None and attempt.plan_id == abort.plan_id:
                self.publish_outcome(self.executor.abort(abort.reason))
            else:
                self.counters["aborts ignored: not executing"] += 1
        if splice is not None:
            try:
                if self.executor is None:
                    raise ValueError("no scene yet")
                self.executor.splice(splice[1], splice[0])
                self.counters["updates spliced"] += 1
            except ValueError:
                self.counters["updates ignored: not executing"] += 1

    def start_attempt(self) -> None:
        """Start the plan approved in this frame, at the frame's end, where every ground truth
        before the frame is in the scene: the same moment in every lockstep run (the go itself
        may come before or after some of them, on another subscriber)."""
        attempt, self._go = self._go, None
        if attempt is None or self.world is None:
            return
        if self.trial >= self.cfg.trials:
            self.counters["ignored: trials over"] += 1
            return
        if self.executor is None or self.executor.attempt is not None:
            self.counters["ignored: busy" if self.executor else "ignored: no scene yet"] += 1
            return
        attempt.approved_at = self.world.time_s
        self.executor.start(attempt)
        self.attempt += 1
        self._executing = attempt.plan_id
        self.counters["attempts"] += 1

    # --- the scene ----------------------------------------------------------------------

    def advance(self, t_s: float, position: np.ndarray, quat: np.ndarray) -> None:
        self._pose = (t_s, position, quat)
        if self.world is None or self.executor is None:
            return
        if t_s <= self.world.time_s:
            return  # a repeated or older stamp: the scene already is there
        if t_s - self.world.time_s > 1.0:  # a gap in the recording: jump, do not simulate it
            self.world.time_s = t_s - STEP_S
        result = self.executor.advance(t_s, position, quat)
        if result is not None:  # published with the frame, so lockstep runs see it alike
            self._results.append(result)

    def build(self) -> bool:
        """Create the scene once the arm's mount, the object's size and pose are known (at a
        frame's acknowledgement, so a lockstep run builds it at the same moment each time)."""
        if self.shape is None or self._pose is None:
            return False
        t_s, position, quat = self._pose
        try:
            T_world_base = self.tf.lookup("world", self.arm.base_link)
        except ValueError:
            return False
        self.world = SimWorld(self.arm, T_world_base, self.shape, self.cfg.drive_force_n,
                              gui=self.cfg.gui)
        self.world.place_object(position, quat)
        self.world.time_s = t_s
        if self.cfg.tether and not self.world.add_tether():
            log.warning("no tether: the object's lower end does not point down to the seabed")
        self.executor = Executor(self.world)
        return True

    # --- outputs ------------------------------------------------------------------------

    def publish_outcome(self, result: Result) -> None:
        """Publish an attempt's result; a success or the last attempt ends the trial."""
        self.counters["success" if result.success else "aborted" if result.aborted
                      else f"failure: {result.failure}"] += 1
        self._executing = None
        assert self.world is not None
        self.bus.publish(OUTCOME_KEY, GraspOutcome(
            header=new_header(self.name, self.attempt, int(round(self.world.time_s * 1e9))),
            plan_id=result.plan_id, trial=self.trial, attempt=self.attempt,
            success=result.success, failure=result.failure, evidence=result.evidence,
            aborted=result.aborted))
        self._idle_since = self.world.time_s
        if result.success or self.attempt >= self.cfg.attempts:
            self.trial += 1
            self.attempt = 0
        if self.trial >= self.cfg.trials and self.cfg.stop_after_trials:
            log.info("%d trials done: stopping", self.trial)
            self.stop(0)

    def check_trial_timeout(self) -> None:
        """End a trial that has waited ``trial_timeout_s`` for an approved plan."""
        assert self.world is not None and self.executor is not None
        if (self._idle_since is None or self.executor.busy or self.trial >= self.cfg.trials
                or self.world.time_s - self._idle_since < self.cfg.trial_timeout_s):
            return
        self.counters["trials ended waiting for a plan"] += 1
        trial = self.trial
        self.publish_outcome(Result("", False, "other", {
            "reason": f"no plan approved for {self.cfg.trial_timeout_s:.0f} s",
            "no_attempt": True}))
        if self.trial == trial:  # not its last attempt, but the trial is over all the same
            self.trial, self.attempt = self.trial + 1, 0
            if self.trial >= self.cfg.trials and self.cfg.stop_after_trials:
                self.stop(0)

    def finish_frame(self, frame_seq: int) -> None:
        if self.world is None and not self.build():
            return
        assert self.world is not None
        for result in self._results:
            self.publish_outcome(result)
        self._results.clear()
        if self._idle_since is None and self._plans_flow:  # trial 0 begins
            self._idle_since = self.world.time_s
        self.follow_paths()
        self.start_attempt()
        self.apply_abort_and_update()
        if self.executor is not None:
            self.check_trial_timeout()
            if self._mesh is not None and not self.executor.busy:
                self.world.use_mesh(self._mesh)
                self._mesh = None
                self.counters["meshes used"] += 1
        q, qd = self.world.arm_q()
        self.bus.publish(ARM_STATE_KEY, ArmState(
            header=new_header(self.name, frame_seq, int(round(self.world.time_s * 1e9))),
            joint_names=list(self.arm.joint_names), positions=q.tolist(),
            velocities=qd.tolist(), jaw_opening_m=self.world.jaw_opening(),
            executing_plan_id=self._executing,
            returning=self.executor is not None and self.executor.returning))
        fq, fqd = self.world.finger_q()
        self.bus.publish_cdr(self.cfg.joint_states_key, encode_joint_state(
            int(round(self.world.time_s * 1e9)), [*self.arm.joint_names, *self.arm.jaw_joints],
            np.concatenate([q, fq]), np.concatenate([qd, fqd])), JOINT_STATE)
        self.note_state()

    def on_stop(self) -> None:
        self.state.clear()  # stopped, not crashed: the next run starts afresh
        if self.world is not None:
            self.world.close()


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="wavegrasp sim", description=__doc__)
    parser.add_argument("--gui", action="store_true", help="open PyBullet's window")
    args = parser.parse_args(argv)
    try:
        settings = SimSettings.from_env("sim", **({"gui": True} if args.gui else {}))
        service = SimService(settings)
    except ValueError as exc:
        print(f"wavegrasp sim: {exc}", file=sys.stderr)
        return 2
    setup_logging(settings.log_level)
    return service.run()

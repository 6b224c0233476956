"""``wavegrasp planner``: predictions -> a grasp and the timed joint trajectory to it.

For each warm ``wavegrasp/predictor/prediction`` while no approved plan is executing, plans a
grasp (:func:`~wavegrasp.planner.plan.plan_grasp`) for the arm on its mount from ``tf_static``,
starting from the arm's latest ``sensor_msgs/msg/JointState`` (``joint_states``; its home pose
until one arrives) and never while the arm follows a commanded path (the gate's
``JointTrajectory`` to the arm's controller, :class:`~wavegrasp.runtime.settings.ArmTopics`), and
publishes it on ``wavegrasp/planner/plan``. When no grasp can be planned from where the idle arm
is, it asks the arm to move to its standby first (``wavegrasp/planner/standby``). The last
plan's grasp is tried first on the next prediction (:class:`~wavegrasp.planner.plan.Hint`),
until a grasp fails. While the predictor warms up, its forecasts are planned on only to
move the arm to its standby and find the grasp to try first. The arm model is ours unless
``WAVEGRASP_ARM_URDF`` names the vehicle's own description. In real time it plans at most
``max_share`` of the wall time, the newest prediction waiting meanwhile, so a search that
runs long cannot hold the stages before it off a core.
"""

from __future__ import annotations

import argparse
import logging
import sys
import time
from collections import Counter, deque
from dataclasses import replace
from typing import Literal

import numpy as np
from pydantic import Field
from scipy.spatial.transform import Rotation

from wavegrasp.arm import ArmModel
from wavegrasp.checks import StampOrder
from wavegrasp.planner.approach import PredictedPath
from wavegrasp.planner.collision import Body, Turns
from wavegrasp.planner.plan import Hint, Plan, PlannerConfig, plan_grasp
from wavegrasp.planner.standby import standby_move, standby_poses
from wavegrasp.planner.update import update_plan
from wavegrasp.recording_io.ros_msgs import (
    StaticTransforms,
    decode_joint_state,
    decode_joint_trajectory,
    decode_tf,
)
from wavegrasp.runtime.bus import Bus, Delivery
from wavegrasp.runtime.service import Service, setup_logging
from wavegrasp.runtime.settings import ArmTopics, Settings
from wavegrasp.runtime.trace import derived_header, new_header
from wavegrasp.schemas import (
    ArmStandby,
    GateAbort,
    GateDecision,
    GraspOutcome,
    GraspPlan,
    MotionPrediction,
    ObjectObservation,
    Pose,
    PredictionSample,
    Quaternion,
    Vec3,
)

#: Predictions whose data's age judges an update's delay, and what planning, the hop to the
#: gate and its decision add to it (an update plans in about 10 ms, p95).
UPDATE_AGES = 20
GATE_ALLOWANCE_S = 0.015
log = logging.getLogger("wavegrasp.planner")
PLAN_KEY = "wavegrasp/planner/plan"
STANDBY_KEY = "wavegrasp/planner/standby"
STANDBY_AGAIN_NS = 1_000_000_000  # after a standby move ends, before another may be asked
#: Recording seconds the object is seen before the arm is moved to wait by it: longer than
#: the longest swing (2.5 s), so the standby is solved for all of it.
SWAY_SEEN_S = 4.0


#: A body this many times longer than it is wide has an axis worth turning (see
#: :meth:`PlannerService.on_observation`).
LONG = 1.5


class PlannerSettings(Settings, ArmTopics):
    execution: Literal["closed", "open"] = Field("closed", description="closed: while an "
                                                 "approved plan executes, every new warm "
                                                 "prediction moves it (an update, "
                                                 "update_of set); open: the paper's method, "
                                                 "executed as approved")
    execution_hold_s: float = 1.5
    standby_every_s: float = Field(2.0, gt=0.0, description="the standby pose is solved "
                                   "again after this much recording time, if the object's sway "
                                   "or size has changed since by more than standby_moved_m")
    standby_moved_m: float = Field(0.02, ge=0.0, description="see standby_every_s")
    pace: Literal["realtime", "fast", "lockstep"] = Field(
        "realtime", description="the player's (WAVEGRASP_PACE): max_share holds in real time")
    max_share: float = Field(0.5, gt=0.0, le=1.0, description="in real time, of the wall "
                             "time at most this share planning: after a plan or update that "
                             "took t s the next starts no sooner than t / max_share - t s "
                             "later, the newest prediction kept meanwhile. On the top "
                             "real-time priority a planner searching on every prediction "
                             "(every plan late, none approved) held the stages before it and "
                             "the recorder off a core, and a 30 Hz run never caught up")


def to_message(plan: Plan, pred: MotionPrediction, recv_ns: int, arm: ArmModel,
               service: str, standby: np.ndarray | None = None, update_of: str | None = None,
               since: float | None = None) -> GraspPlan:
    """The plan as sent; ``update_of``: the executing plan it moves, its trajectory from
    ``since`` (s) on, where it takes over."""
    ns = lambda t: int(round(t * 1e9))  # noqa: E731
    if since is not None:
        keep = plan.times >= since - 1e-9
        plan = replace(plan, times=plan.times[keep], q=plan.q[keep], qd=plan.qd[keep],
                       tool=plan.tool[keep])
    t_ns = np.rint(plan.times * 1e9).astype(np.int64).tolist()
    grasp, *candidates = poses([plan.grasp_T_world, *plan.candidates])
    # Plain dicts validated at once: a third of the time of building each sample's model.
    return GraspPlan.model_validate(dict(
        header=derived_header(pred.header, service, recv_ns),
        plan_id=f"{pred.header.seq}-{ns(plan.t_grasp)}", t_start_ns=ns(plan.t_start),
        t_grasp_ns=ns(plan.t_grasp),
        grasp=grasp,
        approach=Vec3.of(plan.approach), joint_names=list(arm.joint_names),
        joint_trajectory=[{"t_ns": t, "positions": qi, "velocities": vi}
                          for t, qi, vi in zip(t_ns, plan.q.tolist(), plan.qd.tolist(),
                                               strict=True)],
        cartesian_path=[{"t_ns": t, "x": p[0], "y": p[1], "z": p[2]}
                        for t, p in zip(t_ns, plan.tool.tolist(), strict=True)],
        confidence=plan.confidence, waypoints=[Vec3.of(p) for p in plan.points],
        t_final_ns=ns(plan.t_final), jaw_preshape_m=plan.jaw_preshape_m,
        t_close_ns=ns(plan.t_close), candidates=candidates,
        standby=[] if standby is None else standby.tolist(), update_of=update_of,
        t_contact_ns=None if plan.t_contact is None else ns(plan.t_contact)))


def poses(Ts: list[np.ndarray]) -> list[Pose]:
    """(4, 4) transforms (at least one) as Poses; one rotation conversion for all (scipy's
    per-call cost is most of it)."""
    quats = Rotation.from_matrix(np.stack([T[:3, :3] for T in Ts])).as_quat()
    return [Pose(position=Vec3.of(T[:3, 3]), orientation=Quaternion(x=q[0], y=q[1], z=q[2], w=q[3]))
            for T, q in zip(Ts, quats, strict=True)]


class PlannerService(Service):
    ack_after = "predictor"

    def __init__(self, settings: PlannerSettings, bus: Bus | None = None) -> None:
        self.arm = ArmModel.load(settings.arm_urdf or None)  # before the bus: fail cleanly
        super().__init__(settings, bus)
        self.cfg = settings
        self.config = PlannerConfig(closed_loop=settings.execution == "closed")
        self.tf = StaticTransforms()
        self.q_now = self.arm.q_home.copy()
        self._arm_fast = False  # a joint of the arm moving, in its latest state
        self._state_ns: int | None = None  # the latest state's stamp
        self._commanded_until_ns = 0  # the end of the arm's commanded path
        self.body = Body(0.05)
        self.busy_until_ns = 0
        # The end of the standby move asked for last: no plan before it (the arm will not be
        # where it is), and no other standby move until a second after it.
        self._standby_end_ns = -STANDBY_AGAIN_NS
        #: (solved at, mount, the sway and size it was solved for, the standby poses)
        self._standby: tuple[int, bytes, np.ndarray, list[np.ndarray]] | None = None
        self._choice = 0  # which of the standby poses the arm waits in
        self._probe = 0  # the next of them to plan from while none comes from the chosen one
        #: The standby pose a grasp was planned from before the arm moved there, or that was
        #: taken with none planning (:meth:`standby_plans`), and those tried without a plan.
        self._accepted: int | None = None
        self._tried: set[int] = set()
        self._failing_since_ns: int | None = None  # no plan from the idle arm since
        #: Search every standby pose, even where facing the object solves every grasp: set
        #: once nothing planned from facing for a period (:meth:`probe_standby`).
        self._search_all = False
        #: Where it has been lately (a few seconds of centroids, metres, world).
        self.seen: deque[np.ndarray] = deque(maxlen=100)
        self._seen_ns: deque[int] = deque(maxlen=100)  # their stamps
        #: How a box or long body has been turned lately: (stamp ns, :attr:`Body.orientation`).
        self.frames: deque[tuple[int, np.ndarray]] = deque(maxlen=300)
        self._misfits = 0  # round bodies' axes skipped in a row (:meth:`misfit`)
        self._hint: Hint | None = None  # the last plan's grasp, tried first next time
        #: How old the latest predictions' data was on arrival, wall seconds (:meth:`delay_s`).
        self._ages: deque[float] = deque(maxlen=UPDATE_AGES)
        #: The last plan sent (its id, the plan, the approved plan it updates or None) and,
        #: once the gate approves it, the executing one: updated on every warm prediction
        #: in closed-loop execution.
        self._sent: tuple[str, Plan, str | None] | None = None
        self._executing: tuple[str, Plan] | None = None
        self.bus.subscribe("tf_static", lambda d: self.tf.update(decode_tf(d.payload)))
        self.bus.subscribe("wavegrasp/perception/object", self.on_observation, ObjectObservation)
        self.bus.subscribe(settings.joint_states_key, self.on_joint_states)
        self.bus.subscribe(settings.arm_trajectory_key, self.on_arm_trajectory)
        self.bus.subscribe("wavegrasp/gate/decision", self.on_decision, GateDecision)
        self.bus.subscribe("wavegrasp/gate/abort", self.on_abort, GateAbort)
        self.bus.subscribe("wavegrasp/sim/outcome", self.on_outcome, GraspOutcome)
        self.bus.subscribe("wavegrasp/predictor/prediction", self.on_prediction,
                           MotionPrediction)
        self._t_grasp: dict[str, int] = {}
        self._pending: tuple[MotionPrediction, Delivery] | None = None
        self._rest_until = 0.0  # monotonic s: no planning before (max_share, real time)
        self._order = StampOrder(restart_s=1.0)  # a replay begun again restarts the stream

    def on_observation(self, msg: ObjectObservation, _d: Delivery) -> None:
        if msg.centroid is not None:  # where the object sways: the arm waits facing it
            self.see(np.array([msg.centroid.x, msg.centroid.y, msg.centroid.z]),
                     msg.header.stamp_ns)
        if msg.radius_m is not None:  # the object's size and axis, for the collision check
            self.body = Body.from_observation(msg)
            if self.body.seabed is not None and not self.over(self.body.seabed):
                self.counters["seabed ignored: the arm's mount is not above it"] += 1
                self.body = replace(self.body, seabed=None)
            # A box's faces fix its orientation, a long body's outline its axis: both rock
            # with the waves (a 31 cm bottle 25 degrees either way, and the palm met it
            # where it had turned since the plan). A body nearly as wide as it is long is
            # not turned: its axis is poorly set (a 13 x 15 cm ellipsoid's wandered 6
            # degrees a frame, and the collisions its turns made up left nothing planned)
            # and hardly matters.
            orientation = self.body.orientation
            if orientation is None or (self.body.frame is None
                                       and self.body.half_length < LONG * self.body.radius):
                self.frames.clear()
            elif self.misfit(orientation):
                self.counters["turns: axis misfit skipped"] += 1
            else:
                self.frames.append((msg.header.stamp_ns, orientation))

    def over(self, plane: np.ndarray) -> bool:
        """Is the arm's mount above ``plane`` (a, b, c, d), world, unit normal up? A seabed
        found above it is a misfit (every pose of the arm would be inside it); True while
        the mount is not known yet."""
        try:
            t = self.tf.lookup("world", self.arm.base_link)[:3, 3]
        except ValueError:
            return True
        return float(plane[:3] @ t + plane[3]) > 0.0

    def see(self, centroid: np.ndarray, stamp_ns: int) -> None:
        """The object's centroid, shape (3,), metres, world, observed at ``stamp_ns``."""
        self.seen.append(centroid)
        self._seen_ns.append(stamp_ns)

    def misfit(self, orientation: np.ndarray) -> bool:
        """Is a round body's axis (``orientation``'s third column) a misfit: turned more
        than 45 degrees from the last one kept? Between frames a rocking object turns a few
        degrees (36 degrees either way every 2 s is 11 degrees a frame at 10 Hz); one
        outline fit in a few dozen of a 17 cm cylinder was about an axis 90 degrees off,
        and turned so, the cylinder blocked every approach (random-7-013). After three
        skipped in a row the next is taken: the object did turn."""
        if self.body.frame is not None or not self.frames or self._misfits >= 3:
            self._misfits = 0
            return False
        if abs(float(self.frames[-1][1][:, 2] @ orientation[:, 2])) >= np.cos(np.pi / 4):
            self._misfits = 0
            return False
        self._misfits += 1
        return True

    def turning(self, period_s: float) -> Body:
        """The latest body, turning over the next periods as it turned over the last ones
        (:class:`Turns`): a box, a bottle or a cylinder rocks with the waves, tens of
        degrees."""
        now = self.body.orientation
        if now is None or len(self.frames) < 2 or not period_s > 0:
            return self.body
        times = np.array([t for t, _ in self.frames]) * 1e-9
        frames = np.array([frame for _, frame in self.frames])
        if self.body.frame is None:  # an axis read off an outline points either way
            flip = frames[:, :, 2] @ now[:, 2] < 0
            frames[flip] = frames[flip] @ np.diag([1.0, -1.0, -1.0])
        rotations = frames @ now.T
        return replace(self.body, turns=Turns(times, rotations, period_s))

    def on_joint_states(self, d: Delivery) -> None:
        stamp_ns, names, positions, velocities = decode_joint_state(d.payload)
        missing = [n for n in self.arm.joint_names if n not in names]
        if missing:
            raise ValueError(f"joint_states lacks joints {', '.join(missing)}")
        index = [names.index(n) for n in self.arm.joint_names]
        self.q_now = positions[index]
        self._arm_fast = bool(np.abs(velocities[index]).max(initial=0.0) > 0.02)
        self._state_ns = stamp_ns

    def on_arm_trajectory(self, d: Delivery) -> None:
        """The arm's commanded path (sent by the gate): no plan before its end."""
        names, times, _q, _qd = decode_joint_trajectory(d.payload)
        if sorted(names) != sorted(self.arm.joint_names):
            raise ValueError(f"joint_names {names} are not the arm's {list(self.arm.joint_names)}")
        self._commanded_until_ns = max(self._commanded_until_ns, int(round(times[-1] * 1e9)))

    def arm_moving(self, now_ns: int) -> bool:
        """A plan starts from rest: none while the arm follows a path or moves (as of its
        latest state, else ``now_ns``). Its return to standby starts at rest: planned on
        from where the grasp left it, one prediction found nothing and asked for a standby
        move the returning arm ignored, and the planner waited out that move's 8 s while
        the trial ran out (random-191-000)."""
        at_ns = now_ns if self._state_ns is None else self._state_ns
        return self._arm_fast or at_ns < self._commanded_until_ns

    def on_decision(self, msg: GateDecision, _d: Delivery) -> None:
        if msg.go:
            hold = int(self.cfg.execution_hold_s * 1e9)
            self.busy_until_ns = self._t_grasp.get(msg.plan_id, self.clock.now_ns()) + hold
            if self._sent is not None and self._sent[0] == msg.plan_id:
                plan_id, plan, update_of = self._sent
                self._executing = (update_of or plan_id, plan)

    def on_abort(self, msg: GateAbort, _d: Delivery) -> None:
        if self._executing is not None and self._executing[0] == msg.plan_id:
            self._executing, self._hint = None, None
            self.counters["aborted"] += 1

    def on_outcome(self, msg: GraspOutcome, _d: Delivery) -> None:
        self.busy_until_ns = 0
        self._executing = None
        if not msg.success:  # a grasp that failed is not the one to try first again
            self._hint = None

    def on_prediction(self, msg: MotionPrediction, d: Delivery) -> None:
        """Keep only the newest: planning takes longer than predictions come when candidates
        fail, and a plan from an older prediction would only be late (one that comes after a
        newer one is refused)."""
        self._order.check(msg.header.stamp_ns)
        if msg.header.trace and self.clock.rate > 0:
            self._ages.append(max(0.0, (d.recv_ns - msg.header.trace[0].recv_ns) / 1e9
                                  * self.clock.rate))
        if self._pending is not None:
            self.counters["skipped: superseded"] += 1
        self._pending = (msg, d)

    def on_start(self) -> None:
        try:
            self.self_check()
        except Exception as exc:  # a check, not a reason to stop: real plans may still work
            log.warning("self-check failed: %s: %s", type(exc).__name__, exc)

    def self_check(self) -> None:
        """Plan once, before the first frame, for an object swaying in front of the arm's
        shoulder (in its own base frame), and log how that went: an arm description that
        cannot plan there shows at start. It also spares the first real plan the set-up its
        libraries do on first use (LAPACK, ruckig, the plan's serialiser): a first plan took
        about 27 ms against 6 ms for the next."""
        started = time.perf_counter()
        t = np.arange(41) * 0.1
        sway = np.column_stack([0.05 * np.sin(2 * np.pi * t / 1.2),
                                0.02 * np.sin(2 * np.pi * t / 1.2),
                                0.02 * np.cos(2 * np.pi * t / 1.2)])
        centre = self.arm.shoulder + self.arm.reach_m * np.array([0.55, 0.0, -0.1])
        samples = [PredictionSample(t_ns=int(round(ti * 1e9)), x=p[0], y=p[1], z=p[2],
                                    sigma=0.002) for ti, p in zip(t, centre + sway, strict=True)]
        pred = MotionPrediction(header=new_header(self.name, 0, 0), model="self-check",
                                period_s=1.2, samples=samples, warm=True)
        result = plan_grasp(PredictedPath.from_message(pred), 0.0, self.arm, np.eye(4),
                            self.arm.q_home.copy(), Body(0.04), self.config)
        if isinstance(result, Plan):
            to_message(result, pred, 0, self.arm, self.name).model_dump_json()
            log.info("self-check: planned a grasp %.2f m from the shoulder in %.0f ms",
                     np.linalg.norm(centre - self.arm.shoulder),
                     (time.perf_counter() - started) * 1e3)
        else:
            log.warning("self-check: no grasp %.2f m in front of the shoulder (%s); the arm "
                        "description may not suit the planner",
                        np.linalg.norm(centre - self.arm.shoulder),
                        ", ".join(f"{k} {n}" for k, n in result.items()))

    def finish_frame(self, frame_seq: int) -> None:
        self.on_tick()  # plan on the frame's prediction before acknowledging the frame

    def on_tick(self) -> None:
        realtime = self.cfg.pace == "realtime"
        if self._pending is not None and not (realtime and time.monotonic() < self._rest_until):
            msg, d = self._pending
            self._pending = None
            started = time.monotonic()
            try:
                self.plan(msg, d)
            except ValueError as exc:
                self.bus.count_bad("wavegrasp/predictor/prediction", str(exc))
            except Exception as exc:  # a planner bug on one prediction must not end the loop
                log.exception("planning failed on prediction %d", msg.header.seq)
                self.bus.count_bad("wavegrasp/predictor/prediction",
                                   f"{type(exc).__name__}: {exc}"[:300])
            if realtime:
                now = time.monotonic()
                self._rest_until = now + (now - started) * (1.0 / self.cfg.max_share - 1.0)

    def plan(self, msg: MotionPrediction, d: Delivery) -> None:
        if self._executing is not None and msg.header.stamp_ns * 1e-9 > (
                self._executing[1].t_grasp + self.cfg.execution_hold_s):
            self._executing = None  # its outcome never came (an arm that did not take it)
        if self._executing is not None and self.cfg.execution == "closed" and msg.warm:
            self.update(msg, d)
            return
        if msg.header.stamp_ns < self.busy_until_ns or self.arm_moving(msg.header.stamp_ns):
            self.counters["skipped: warming up" if not msg.warm else "skipped: executing"] += 1
            self._failing_since_ns = None
            return
        if msg.header.stamp_ns < self._standby_end_ns:
            # Until the arm has started the move it asked for it still looks idle; a plan
            # from here would be approved and then refused by an arm moving elsewhere
            # (measured: two trials lost waiting for a grasp that never started).
            self.counters["skipped: standby move"] += 1
            return
        try:
            T_world_base = self.tf.lookup("world", self.arm.base_link)
        except ValueError as exc:
            self.counters["skipped: no arm mount"] += 1
            raise ValueError(f"no transform to the arm's mount: {exc}") from None
        path = PredictedPath.from_message(msg)
        # A forecast still warming up is not corrected on the way: it only finds the standby
        # and the grasp to try first, by what it trusts (closed loop's less trusted grasp
        # times set that grasp 4 s ahead on the tank, where 2.8 s ones plan).
        config = self.config if msg.warm else self.config.model_copy(update={"closed_loop": False})
        result = plan_grasp(path, msg.header.stamp_ns * 1e-9, self.arm, T_world_base,
                            self.q_now, self.turning(path.period_s), config, self._hint)
        if not msg.warm:
            self.rehearse(msg, d, path, T_world_base, result)
            return
        if not isinstance(result, Plan):
            self.counters["no plan"] += 1
            for reason, n in result.items():
                self.counters[f"rejected: {reason}"] += n
            self.ask_standby(msg, d, path, T_world_base, result)
            return
        self.counters["plans"] += 1
        self._failing_since_ns = None
        self._hint = Hint.of(result, path)
        plan = to_message(result, msg, d.recv_ns, self.arm, self.name,
                          self.return_pose(T_world_base, msg.header.stamp_ns))
        self._t_grasp = {plan.plan_id: plan.t_grasp_ns}
        self._sent = (plan.plan_id, result, None)
        self.bus.publish(PLAN_KEY, plan)

    def update(self, msg: MotionPrediction, d: Delivery) -> None:
        """Closed loop: move the executing plan to this prediction
        (:func:`~wavegrasp.planner.update.update_plan`) and send it as an update of it."""
        assert self._executing is not None
        root, plan = self._executing
        if msg.header.stamp_ns * 1e-9 >= plan.t_grasp:
            self.counters["skipped: executing"] += 1
            return
        T_world_base = self.tf.lookup("world", self.arm.base_link)
        path = PredictedPath.from_message(msg)
        now = msg.header.stamp_ns * 1e-9
        delay_s = self.delay_s()
        config = self.config.model_copy(update={"update_delay_s": delay_s})
        result = update_plan(plan, path, now, self.arm, T_world_base,
                             self.turning(path.period_s), config)
        if isinstance(result, str):
            self.counters[f"update: {result}"] += 1
            return
        self.counters["updates"] += 1
        if result.t_contact is not None:
            self.counters["updates: contact ahead"] += 1
        standby = self.return_pose(T_world_base, msg.header.stamp_ns)
        sent = to_message(result, msg, d.recv_ns, self.arm, self.name, standby, update_of=root,
                          since=now + delay_s)
        self._t_grasp = {sent.plan_id: sent.t_grasp_ns}
        self._sent = (sent.plan_id, result, root)
        self.bus.publish(PLAN_KEY, sent)

    def delay_s(self) -> float:
        """How long after its prediction an update takes over: ``update_delay_s``, or more
        where the data comes late. The gate approves an update only if it takes over at
        least as long from its decision as the data took to reach it (the time for the path
        to reach the arm), so with data reaching the gate ``L`` s after the camera the update
        must take over at least ``2 L`` after the frame: across a tether L was 60-80 ms and
        every update at 100 ms was refused. ``L`` is judged by the oldest of the last
        predictions' arrivals (their traces: the camera's publish time to here, at the
        recording's rate), and what the gate adds after here."""
        latest = max(self._ages, default=0.0) + GATE_ALLOWANCE_S
        return max(self.config.update_delay_s, 2 * latest)

    def rehearse(self, msg: MotionPrediction, d: Delivery, path: PredictedPath,
                 T_world_base: np.ndarray, result: Plan | Counter) -> None:
        """A forecast of a predictor still warming up is not acted on, but it shows where the
        object goes: planned on as a warm one, it moves the idle arm to its standby (keeping
        clear of everywhere the object has been seen) and finds the standby pose and the
        grasp that plan, so the first warm forecast is planned from there. Asked at the first
        warm forecast, the standby move took 1-7 s (seed 7's suite: 12 of 31 scenarios; one
        trial lost waiting for the first plan)."""
        self.counters["skipped: warming up"] += 1
        if isinstance(result, Plan):
            self.counters["warming up: planned"] += 1
            self._hint, self._failing_since_ns = Hint.of(result, path), None
        else:
            self.counters["warming up: no plan"] += 1
            self.ask_standby(msg, d, path, T_world_base, result)

    def standby(self, T_world_base: np.ndarray, stamp_ns: int) -> np.ndarray:
        """The standby pose: the chosen one of :func:`standby_poses` (the first, until
        :meth:`probe_standby` finds a better one), solved again once ``standby_every_s`` of
        recording time has passed and the object's sway (where it is, how far it goes) or
        its size changed by ``standby_moved_m``, or the mount moved: it takes a few dozen
        inverse kinematics (about 0.5 s measured), and where the object sways changes over
        seconds, not frames. A pose the probes chose stays chosen while one solved again is
        within ``standby_tolerance_rad`` of it: a swing seen in part moves its sway by more
        than 2 cm every few seconds, and each time the arm was sent back to the first pose,
        from which nothing planned (random-83-002: the pose that plans found 19 s into the
        recording and left at 25 s)."""
        key = T_world_base.tobytes()
        seen = np.array(self.seen).reshape(-1, 3)
        sway = np.concatenate([seen.mean(axis=0), np.ptp(seen, axis=0), [self.body.half_size]]
                              ) if len(seen) else np.zeros(7)
        cached = self._standby
        if cached is None or cached[1] != key or stamp_ns < cached[0] or (
                stamp_ns - cached[0] >= self.cfg.standby_every_s * 1e9
                and np.abs(sway - cached[2]).max() > self.cfg.standby_moved_m):
            probed = cached[3][self._choice] if cached and cached[1] == key and self._choice \
                else None
            poses = standby_poses(self.arm, T_world_base, seen, self.body,
                                  search_all=self._search_all, cfg=self.config)
            self._standby = cached = (stamp_ns, key, sway, poses or [self.arm.q_home.copy()])
            self._choice, self._probe, self._failing_since_ns = 0, 0, None
            self._accepted, self._tried = None, set()
            if probed is not None:
                off = [float(np.abs(q - probed).max()) for q in cached[3]]
                if min(off) < self.config.standby_tolerance_rad:
                    self._choice = int(np.argmin(off))
        return cached[3][self._choice].copy()

    def return_pose(self, T_world_base: np.ndarray, stamp_ns: int) -> np.ndarray:
        """Where the arm waits after the grasp it is planned for: its standby once accepted
        (a grasp planned from there, or every pose tried without one: :meth:`standby_plans`,
        :meth:`probe_standby`), else the pose this grasp was planned from. A grasp planned
        from the home pose carried the first ranked standby, untested: random-131-017's arm
        returned there after its first grasp, nothing planned from it, and the second trial
        was lost (no plan approved for 5 s)."""
        q = self.standby(T_world_base, stamp_ns)
        return q if self._accepted == self._choice else self.q_now.copy()

    def other_standbys(self, j: int) -> list[np.ndarray]:
        """The standby poses but the ``j``-th: clear of the object, so a move may stop at
        one on its way to the ``j``-th."""
        poses = self._standby[3] if self._standby is not None else []
        return [q for k, q in enumerate(poses) if k != j]

    def probe_standby(self, msg: MotionPrediction, path: PredictedPath,
                      T_world_base: np.ndarray, swept: np.ndarray | None = None
                      ) -> tuple[np.ndarray, ...] | None:
        """Nothing has been planned from where the idle arm is, at its standby or unable to
        move there, for a whole period of the motion (every phase of a swing tried): plan
        once from the next of the other standby poses, and if that plans and the arm can move
        there now clear of the object, wait there instead: returns that move
        (:func:`standby_move`). Whether grasps plan from a pose is only known by planning
        them (the ranking of :func:`standby_poses` guesses it from the grasps' joints alone,
        and a 13 cm sphere in the 14 cm jaw plans only head-on along its motion:
        random-7-034, 0 of 8 predictions planned from the first pose, 4 of 8 from the
        fourth). One plan per prediction at most. ``swept``: as :func:`standby_move`'s."""
        now_ns = msg.header.stamp_ns
        if self._standby is None or self._failing_since_ns is None or (
                now_ns - self._failing_since_ns < path.period_s * 1e9):
            return None
        if len(self._standby[3]) < 2 and not self._search_all:  # facing alone: search
            self._search_all, self._standby, failing = True, None, self._failing_since_ns
            self.standby(T_world_base, now_ns)
            self._failing_since_ns = failing
        poses = self._standby[3]
        if len(poses) < 2:
            return None
        self._probe = self._probe % len(poses)
        if self._probe == self._choice:
            self._probe = (self._probe + 1) % len(poses)
        j = self._probe
        self._probe += 1
        self.counters["standby probes"] += 1
        if not self.plans_from(poses[j], path, now_ns, T_world_base):
            return None
        move = standby_move(self.arm, T_world_base, self.q_now, poses[j], path, now_ns * 1e-9,
                            self.body, self.config, via=self.other_standbys(j), swept=swept)
        if isinstance(move, str):  # tried again when its turn comes round
            self.counters[f"standby probe: move {move}"] += 1
            return None
        self.counters["standby changed"] += 1
        self._choice, self._accepted, self._failing_since_ns = j, j, None
        return move

    def plans_from(self, q: np.ndarray, path: PredictedPath, now_ns: int,
                   T_world_base: np.ndarray) -> bool:
        """Does a grasp plan from the arm at ``q`` (radians, shape (n,)) on ``path``? If so,
        it is the grasp tried first on the next prediction. Where the prediction trusts no
        grasp time at all (a predictor that has measured none of its errors yet), it is
        taken as trusting the leads searched first (``soon_s``): the question is what the
        arm reaches from ``q``, and the forecast still says where the object goes. Taken as
        "nothing plans", such forecasts tried every pose and sent random-197-006's arm to the
        first-ranked one; waiting for a trusted forecast, the arm tested its poses only once
        the predictor was warm, and its first five warm predictions planned nothing; trusted
        at every lead, they chose a pose from which only grasps 5 s ahead planned."""
        now_s = now_ns * 1e-9

        def plan(path: PredictedPath) -> Plan | Counter:
            return plan_grasp(path, now_s, self.arm, T_world_base, q,
                              self.turning(path.period_s), self.config)

        result = plan(path)
        if not isinstance(result, Plan) and set(result) == {"prediction too uncertain"}:
            soon = path.times_s <= now_s + self.config.soon_s
            result = plan(replace(path, sigma=np.where(soon, 0.0, np.inf)))
        if isinstance(result, Plan):
            self._hint = Hint.of(result, path)
            return True
        return False

    def standby_plans(self, path: PredictedPath, now_ns: int, T_world_base: np.ndarray
                      ) -> bool:
        """Before the idle arm moves to its standby: does a grasp plan from there? If not,
        the next pose not yet tried is chosen, to be tried on the next prediction; once
        every pose has been tried without a plan, the first is taken (the probes look on from
        there). One plan per prediction. The ranking of :func:`standby_poses` guesses from
        the grasps' joints alone: random-113-034's first pose planned none of 43 warm
        predictions, its second all of them, and the arm moved 2.9 s to the first and
        waited there 2.2 s before the probes found the second."""
        if self._standby is None or self._accepted == self._choice:
            return True
        poses = self._standby[3]
        self.counters["standby tests"] += 1
        if self.plans_from(poses[self._choice], path, now_ns, T_world_base):
            self._accepted = self._choice
            return True
        self._tried.add(self._choice)
        untried = [j for j in range(len(poses)) if j not in self._tried]
        if untried:
            self._choice = untried[0]
            return False
        self._choice = self._accepted = 0
        return True

    def ask_standby(self, msg: MotionPrediction, d: Delivery, path: PredictedPath,
                    T_world_base: np.ndarray, rejected: Counter) -> None:
        """No plan from where the idle arm is (``rejected``: why): have it move to its
        standby first, once the object has been seen a while and unless a move asked for
        earlier is still under way. A forecast that trusts no grasp time says nothing of the
        pose: it starts no probes of the others (:meth:`probe_standby`). The paper's linear
        predictor trusts none ever, and its arm tried pose after pose, 0.13 s of planning
        each: 27 of the 37 s `wavegrasp replan` spent on one of its runs."""
        now_ns = msg.header.stamp_ns
        if set(rejected) == {"prediction too uncertain"}:
            self._failing_since_ns = None
        elif self._failing_since_ns is None or now_ns < self._failing_since_ns:
            self._failing_since_ns = now_ns  # counted from the first, not a second after a move
        seen_s = (self._seen_ns[-1] - self._seen_ns[0]) * 1e-9 if self._seen_ns else 0.0
        if (seen_s < SWAY_SEEN_S and len(self.seen) < self.seen.maxlen) or (
                now_ns < self._standby_end_ns + STANDBY_AGAIN_NS):
            return
        swept = None if msg.warm else np.array(self.seen)  # a forecast not yet trusted
        q_standby = self.standby(T_world_base, now_ns)
        if np.abs(q_standby - self.q_now).max() >= self.config.standby_tolerance_rad and (
                not self.standby_plans(path, now_ns, T_world_base)):
            return
        q_standby = self.standby(T_world_base, now_ns)
        move = standby_move(self.arm, T_world_base, self.q_now, q_standby, path,
                            now_ns * 1e-9, self.body, self.config,
                            via=self.other_standbys(self._choice), swept=swept)
        if isinstance(move, str):  # there already, or it cannot get there now
            move = self.probe_standby(msg, path, T_world_base, swept) or move
        if isinstance(move, str):
            if move != "already there":
                self.counters[f"standby move: {move}"] += 1
            return
        times, q, qd = move
        t_ns = np.rint(times * 1e9).astype(np.int64)
        self._standby_end_ns = int(t_ns[-1])
        self.counters["standby moves"] += 1
        self.bus.publish(STANDBY_KEY, ArmStandby.model_validate(dict(
            header=derived_header(msg.header, self.name, d.recv_ns), t_start_ns=int(t_ns[0]),
            joint_names=list(self.arm.joint_names),
            joint_trajectory=[{"t_ns": t, "positions": qi, "velocities": vi}
                              for t, qi, vi in zip(t_ns.tolist(), q.tolist(), qd.tolist(),
                                                   strict=True)],
            reason="no grasp can be planned from where the arm is")))


def main(argv: list[str] | None = None) -> int:
    argparse.ArgumentParser(prog="wavegrasp planner", description=__doc__).parse_args(argv)
    try:
        settings = PlannerSettings.from_env("planner")
        service = PlannerService(settings)
    except ValueError as exc:
        print(f"wavegrasp planner: {exc}", file=sys.stderr)
        return 2
    setup_logging(settings.log_level)
    return service.run()

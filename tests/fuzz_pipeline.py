"""How the fuzz test (``test_fuzz.py``) feeds the pipeline's services: perception, predictor,
planner and gate."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np

from wavegrasp.arm import ArmModel
from wavegrasp.gate.main import GateService, GateSettings
from wavegrasp.perception.main import PerceptionService, PerceptionSettings
from wavegrasp.planner.main import PlannerService, PlannerSettings
from wavegrasp.predictor.main import PredictorService, PredictorSettings
from wavegrasp.runtime.bus import CDR
from wavegrasp.runtime.service import Service
from wavegrasp.schemas import (
    ArmStandby,
    Clock,
    GateAbort,
    GateDecision,
    GraspOutcome,
    GraspPlan,
    JointSample,
    MotionPrediction,
    ObjectObservation,
    Pose,
    PredictionSample,
    Vec3,
)

from conftest import wait_until
from fuzz_cases import (
    JOINT_STATE_ENC,
    TRAJECTORY_ENC,
    Case,
    attachment,
    cloud_cdr,
    cloud_semantic_cases,
    header,
    huge_cloud_case,
    joint_state_cdr,
    joint_state_semantic_cases,
    message_case,
    trajectory_cdr,
    trajectory_semantic_cases,
)
from fuzz_harness import Harness, Scenario


class PerceptionScenario(Scenario):
    name = "perception"

    def make(self) -> Service:
        self.frame = 0  # the next camera frame of the sample to send
        return PerceptionService(PerceptionSettings.from_env("perception", env=self.env))

    def frame_case(self, k: int | None = None, kind: str = "valid") -> Case:
        """Camera frame ``k`` of the sample (the next one by default), as the player sends it."""
        if k is None:
            k, self.frame = self.frame, self.frame + 1
            self.t_ns = self.sample.frames[k].log_time_ns
        m = self.sample.frames[k]
        return Case(kind, m.cdr, f"{CDR};{m.msgtype}", None, attachment(k, m.log_time_ns))

    def tracked(self, h: Harness) -> None:
        """The newest frame's observation has a centroid within 5 mm of the truth."""
        obs = h.wait_for("wavegrasp/perception/object",
                         lambda o: o.header.stamp_ns == self.t_ns)
        assert obs.centroid is not None, obs.reason
        c = obs.centroid
        err = np.linalg.norm([c.x, c.y, c.z] - self.sample.truth_at(self.t_ns))
        assert err < 0.005, f"centroid {err * 1e3:.1f} mm from the truth"

    def before(self, h: Harness) -> None:
        self.observations = h.collect("wavegrasp/perception/object", ObjectObservation)
        h.deliver("tf_static", [self.valid("tf_static")])
        h.deliver("trisect/points", [self.frame_case() for _ in range(5)])
        self.tracked(h)

    def valid(self, key: str) -> Case:
        if key == "trisect/points":
            return self.frame_case()
        if key == "tf_static":
            return Case("valid", self.sample.tf, f"{CDR};tf2_msgs/msg/TFMessage", None)
        return super().valid(key)

    def cdr_basis(self, key: str) -> bytes:
        return self.sample.frames[0].cdr if key == "trisect/points" else super().cdr_basis(key)

    def semantic(self, key: str) -> list[Case]:
        if key != "trisect/points":
            return super().semantic(key)
        return [*cloud_semantic_cases(self.sample.camera_points(0), self.t_ns + 1),
                huge_cloud_case(self.t_ns + 2)]

    def odd(self, key: str) -> list[Case]:
        if key != "trisect/points":
            return super().odd(key)
        last, stamps = self.frame - 1, [m.log_time_ns for m in self.sample.frames]
        enc = f"{CDR};sensor_msgs/msg/PointCloud2"
        spotty = self.sample.camera_points(self.frame).copy()
        spotty[::5] = np.nan
        spotty[1::7] = np.inf
        self.frame += 1
        self.t_ns = stamps[self.frame - 1]
        return [
            replace(self.frame_case(last), kind="duplicate frame",
                    reason=rf"duplicate: stamp {stamps[last]} <= last {stamps[last]}"),
            replace(self.frame_case(last - 2), kind="older frame",
                    reason=rf"out of order: stamp {stamps[last - 2]} <= last {stamps[last]}"),
            Case("a third of the points NaN or inf", cloud_cdr(spotty, self.t_ns), enc, None),
            Case("no points", cloud_cdr(np.zeros((0, 3)), self.t_ns + 1), enc, None),
            Case("only NaN points", cloud_cdr(np.full((50, 3), np.nan), self.t_ns + 2), enc,
                 None),
        ]

    def after(self, h: Harness) -> None:
        h.deliver("trisect/points", [self.frame_case() for _ in range(3)])
        self.tracked(h)
        reasons = [o.reason for o in self.observations if o.reason]
        assert reasons.count("empty cloud") == 2, reasons  # no points; only NaN points
        # a refused frame is still reported, without a centroid: every frame is accounted for
        assert sum(r.startswith(("duplicate: stamp", "out of order: stamp")) for r in
                   reasons) == 2, reasons
        assert h.service.counters["nonfinite_points"] > 50
        assert h.timings["trisect/points"] < 10, "the huge cloud was processed, not refused"


class PredictorScenario(Scenario):
    name = "predictor"
    PERIOD_S = 1.5

    def make(self) -> Service:
        self.k = 0  # observations made
        return PredictorService(PredictorSettings.from_env("predictor", env=self.env))

    def motion(self, t_ns: int) -> np.ndarray:
        t = (t_ns - self.sample.frames[0].log_time_ns) * 1e-9
        w = 2 * math.pi / self.PERIOD_S
        return np.array([0.1 + 0.05 * math.sin(w * t), -0.3, 0.5 + 0.03 * math.sin(w * t + 1)])

    def observation(self, t_ns: int | None = None) -> ObjectObservation:
        if t_ns is None:
            self.k += 1
            self.t_ns = t_ns = self.sample.frames[0].log_time_ns + self.k * 10**8
        p = self.motion(t_ns)
        return ObjectObservation(header=header(t_ns, self.k),
                                 centroid=Vec3(x=p[0], y=p[1], z=p[2]), points_used=400,
                                 quality=1.0, sigma_m=0.001)

    def feed(self, h: Harness, n: int) -> MotionPrediction:
        h.deliver("wavegrasp/perception/object",
                  [message_case("valid", self.observation()) for _ in range(n)])
        return h.wait_for("wavegrasp/predictor/prediction",
                          lambda p: p.header.stamp_ns == self.t_ns)

    def before(self, h: Harness) -> None:
        self.predictions = h.collect("wavegrasp/predictor/prediction", MotionPrediction)
        self.feed(h, 40)

    def valid(self, key: str) -> Case:
        if key == "wavegrasp/perception/object":
            return message_case("valid", ObjectObservation(header=header(self.t_ns),
                                                           reason="object not found"))
        return super().valid(key)

    def odd(self, key: str) -> list[Case]:
        if key != "wavegrasp/perception/object":
            return super().odd(key)
        t = self.t_ns
        return [message_case("duplicate observation", self.observation(t),
                             rf"duplicate: stamp {t} <= last {t}"),
                message_case("older observation", self.observation(t - 2 * 10**8),
                             rf"out of order: stamp {t - 2 * 10**8} <= last {t}")]

    def after(self, h: Harness) -> None:
        fuzzed_until = self.t_ns
        self.feed(h, 10)
        assert h.service.model.updates == 50, "only the valid observations reach the model"
        fresh = [p for p in self.predictions if p.header.stamp_ns > fuzzed_until]
        assert len(fresh) == 10
        for pred in fresh:
            first = pred.samples[0]
            assert first.t_ns == pred.header.stamp_ns
            err = np.linalg.norm([first.x, first.y, first.z] - self.motion(first.t_ns))
            assert err < 0.01, f"prediction {err * 1e3:.1f} mm off at lead 0"


class PlannerScenario(Scenario):
    name = "planner"

    def make(self) -> Service:
        self.i = 0  # the truth sample the latest prediction starts at
        self.arm = ArmModel.load(None)
        return PlannerService(PlannerSettings.from_env("planner", env=self.env))

    def prediction(self, warm: bool = True) -> MotionPrediction:
        self.i += 5
        self.t_ns = int(self.sample.truth_ns[self.i])
        return self.sample.prediction(self.i, warm, seq=self.i)

    def joint_state(self, kind: str = "valid") -> Case:
        """The arm at rest at home, its fingers too, as ros2_control's broadcaster says."""
        names = [*self.arm.joint_names, *self.arm.jaw_joints]
        return Case(kind, joint_state_cdr(self.t_ns, names, [*self.arm.q_home, 0.0, 0.0],
                                          [0.0] * len(names)), JOINT_STATE_ENC, None)

    def trajectory(self, kind: str = "valid", ends_s: float = -1.0) -> Case:
        """The arm's commanded path, ending ``ends_s`` from now (before: it is idle)."""
        q = list(self.arm.q_home)
        start_ns = self.t_ns + int((ends_s - 2.0) * 1e9)
        return Case(kind, trajectory_cdr(start_ns, list(self.arm.joint_names),
                                         [(0.0, q), (2.0, q)]), TRAJECTORY_ENC, None)

    def plan_once(self, h: Harness) -> GraspPlan:
        """With the arm at rest and no plan executing, a warm prediction gets its plan."""
        h.send_msg("wavegrasp/sim/outcome", GraspOutcome(header=header(self.t_ns), plan_id="x",
                                                         trial=0, attempt=1, success=False))
        h.send("joint_states", self.joint_state())
        pred = self.prediction()
        h.send_msg("wavegrasp/clock", Clock(header=header(self.t_ns), rate=0.0))
        h.send_msg("wavegrasp/predictor/prediction", pred)
        return h.wait_for("wavegrasp/planner/plan", lambda p: p.header.stamp_ns == self.t_ns)

    def before(self, h: Harness) -> None:
        h.collect("wavegrasp/planner/plan", GraspPlan)
        h.deliver("tf_static", [self.valid("tf_static")])
        self.plan_once(h)

    def valid(self, key: str) -> Case:
        t = self.t_ns
        if key == "tf_static":
            return Case("valid", self.sample.tf, f"{CDR};tf2_msgs/msg/TFMessage", None)
        if key == "wavegrasp/perception/object":
            return message_case("valid", ObjectObservation(header=header(t), reason="no object"))
        if key == "joint_states":
            return self.joint_state()
        if key == "arm/joint_trajectory_controller/joint_trajectory":
            return self.trajectory()
        if key == "wavegrasp/gate/decision":
            return message_case("valid", GateDecision(header=header(t), plan_id="x", go=False,
                                                      mean_error_m=None, threshold_m=0.01,
                                                      window_s=2.0))
        if key == "wavegrasp/sim/outcome":
            return message_case("valid", GraspOutcome(header=header(t), plan_id="x", trial=0,
                                                      attempt=1, success=False))
        if key == "wavegrasp/gate/abort":  # of a plan not executing: nothing to stop
            return message_case("valid", GateAbort(header=header(t), plan_id="x",
                                                   reason="stale prediction"))
        if key == "wavegrasp/predictor/prediction":
            return message_case("valid", self.prediction(warm=False))
        return super().valid(key)

    def semantic(self, key: str) -> list[Case]:
        names, q = list(self.arm.joint_names), list(self.arm.q_home)
        if key == "joint_states":
            return joint_state_semantic_cases(self.t_ns, names, q)
        if key == "arm/joint_trajectory_controller/joint_trajectory":
            return trajectory_semantic_cases(self.t_ns, names, q)
        return super().semantic(key)

    def odd(self, key: str) -> list[Case]:
        t = self.t_ns
        if key == "wavegrasp/predictor/prediction":
            last = self.sample.prediction(self.i, seq=self.i)
            blip = last.model_copy(deep=True, update={"samples": last.samples[:3]})
            blip.header.stamp_ns = t + 1
            for k, s in enumerate(blip.samples):
                s.t_ns = t + 1 + k
            return [message_case("duplicate prediction", last,
                                 rf"duplicate: stamp {t} <= last {t}"),
                    message_case("older prediction", self.sample.prediction(self.i - 3),
                                 rf"out of order: stamp \d+ <= last {t}"),
                    message_case("prediction 2 ns long", blip)]  # no plan in it
        if key == "joint_states":
            return [self.joint_state("duplicate joint state")]
        if key == "arm/joint_trajectory_controller/joint_trajectory":
            return [self.trajectory("a path that ended long ago", -100.0)]
        if key == "wavegrasp/gate/decision":
            go = GateDecision(header=header(t), plan_id="never-planned", go=True,
                              mean_error_m=0.001, threshold_m=0.01, window_s=2.0)
            return [message_case("go for a plan never made", go),
                    message_case("duplicate decision", go)]
        if key == "wavegrasp/sim/outcome":
            out = GraspOutcome(header=header(t - 10**9), plan_id="x", trial=0, attempt=1,
                               success=True)
            return [message_case("old outcome", out), message_case("duplicate outcome", out)]
        return super().odd(key)

    def after(self, h: Harness) -> None:
        n = h.service.counters["plans"]
        plan = self.plan_once(h)
        assert plan.t_grasp_ns > plan.t_start_ns > self.t_ns
        assert h.service.counters["plans"] == n + 1


class GateScenario(Scenario):
    name = "gate"
    PERIOD_S = 4.0
    T0 = 1_000 * 10**9

    def make(self) -> Service:
        self.last_s = 0.0
        return GateService(GateSettings.from_env("gate", env=self.env))

    def ns(self, t_s: float) -> int:
        return self.T0 + round(t_s * 1e9)

    def motion(self, t_s: float) -> np.ndarray:
        w = 2 * math.pi / self.PERIOD_S
        return np.array([0.6 + 0.05 * math.sin(w * t_s), 0.1,
                         -0.4 + 0.03 * math.sin(w * t_s + 1)])

    def observation(self, t_s: float) -> ObjectObservation:
        p = self.motion(t_s)
        return ObjectObservation(header=header(self.ns(t_s)),
                                 centroid=Vec3(x=p[0], y=p[1], z=p[2]), points_used=500,
                                 quality=1.0, sigma_m=0.001)

    def prediction(self, made_s: float) -> MotionPrediction:
        """The true motion from ``made_s`` to 1.5 s ahead."""
        samples = [PredictionSample(t_ns=self.ns(t), x=p[0], y=p[1], z=p[2], sigma=0.005)
                   for t in made_s + 0.05 * np.arange(31) for p in [self.motion(t)]]
        return MotionPrediction(header=header(self.ns(made_s)), model="test",
                                period_s=self.PERIOD_S, samples=samples)

    def plan(self, made_s: float, start_s: float, grasp_s: float, plan_id: str) -> GraspPlan:
        """A plan the arm can follow: holding its home pose from the start to the grasp."""
        g, arm = self.motion(grasp_s), ArmModel.load(None)
        return GraspPlan(header=header(self.ns(made_s)), plan_id=plan_id,
                         t_start_ns=self.ns(start_s), t_grasp_ns=self.ns(grasp_s),
                         grasp=Pose(position=Vec3(x=g[0], y=g[1], z=g[2])),
                         approach=Vec3(x=0, y=0, z=-1), joint_names=list(arm.joint_names),
                         joint_trajectory=[JointSample(t_ns=self.ns(t), positions=list(arm.q_home))
                                           for t in sorted({start_s, grasp_s})])

    def standby(self, t_s: float, names: list[str] | None = None) -> ArmStandby:
        arm = ArmModel.load(None)
        return ArmStandby(header=header(self.ns(t_s)), t_start_ns=self.ns(t_s + 0.1),
                          joint_names=names or list(arm.joint_names),
                          joint_trajectory=[JointSample(t_ns=self.ns(t_s + k / 10),
                                                        positions=list(arm.q_home))
                                            for k in (1, 2)])

    def feed(self, h: Harness, start: int, end: int) -> None:
        """An observation and a prediction every 0.1 s, from ``start`` to ``end`` tenths."""
        for i in range(start, end + 1):
            h.send_msg("wavegrasp/perception/object", self.observation(i / 10))
            h.send_msg("wavegrasp/predictor/prediction", self.prediction(i / 10))
        self.last_s = end / 10

    def decide(self, h: Harness, plan: GraspPlan, now_s: float) -> GateDecision:
        self.t_ns = self.ns(now_s)
        h.send_msg("wavegrasp/clock", Clock(header=header(self.t_ns), rate=0.0))
        h.send_msg("wavegrasp/planner/plan", plan)
        return h.wait_for("wavegrasp/gate/decision", lambda d: d.plan_id == plan.plan_id)

    def before(self, h: Harness) -> None:
        self.tokens = [h.fuzz.session.liveliness().declare_token(f"wavegrasp/health/{s}")
                       for s in ("perception", "predictor", "planner")]
        assert wait_until(lambda: h.service.bus.alive_now() >= {
            "perception", "predictor", "planner"}, timeout=10)
        self.decisions = h.collect("wavegrasp/gate/decision", GateDecision)
        self.feed(h, 0, 30)
        d = self.decide(h, self.plan(3.0, 3.3, 4.0, "a"), now_s=3.05)
        assert d.go, d.reason
        h.send_msg("wavegrasp/sim/outcome", GraspOutcome(header=header(self.ns(3.05)),
                                                         plan_id="a", trial=0, attempt=1,
                                                         success=True))

    def valid(self, key: str) -> Case:
        t_s = self.last_s
        if key == "wavegrasp/perception/object":
            return message_case("valid", ObjectObservation(header=header(self.ns(t_s)),
                                                           reason="no object"))
        if key == "wavegrasp/predictor/prediction":
            return message_case("valid", self.prediction(t_s))
        if key == "wavegrasp/planner/plan":
            return message_case("valid", self.plan(0.0, 0.3, 1.0, "stale"))
        if key == "wavegrasp/sim/outcome":
            return message_case("valid", GraspOutcome(header=header(self.ns(t_s)),
                                                      plan_id="stale", trial=0, attempt=1,
                                                      success=False))
        if key == "wavegrasp/planner/standby":
            return message_case("valid", self.standby(t_s))
        return super().valid(key)

    def odd(self, key: str) -> list[Case]:
        t_s = self.last_s
        if key == "wavegrasp/perception/object":
            return [message_case("duplicate observation", self.observation(t_s),
                                 rf"duplicate: stamp {self.ns(t_s)} <= last {self.ns(t_s)}"),
                    message_case("older observation", self.observation(t_s - 0.5),
                                 rf"out of order: stamp {self.ns(t_s - 0.5)} <= last")]
        if key == "wavegrasp/predictor/prediction":  # kept in stamp order: they score alike
            return [message_case("duplicate prediction", self.prediction(t_s)),
                    message_case("older prediction", self.prediction(t_s - 1.0))]
        if key == "wavegrasp/planner/plan":  # each gets its no-go
            return [message_case("duplicate plan", self.plan(0.0, 0.3, 1.0, "stale")),
                    message_case("plan grasping before it starts",
                                 self.plan(t_s, t_s + 0.5, t_s + 0.3, "backwards"))]
        if key == "wavegrasp/sim/outcome":
            out = GraspOutcome(header=header(self.ns(1.0)), plan_id="a", trial=0, attempt=1,
                               success=True)
            return [message_case("old outcome", out), message_case("duplicate outcome", out)]
        if key == "wavegrasp/planner/standby":
            narrow = self.standby(t_s)
            narrow.joint_trajectory[0].positions = [0.0, 0.0]
            return [message_case("standby for another arm", self.standby(t_s, ["a", "b"]),
                                 r"standby joint_names .* are not the arm's"),
                    message_case("standby of 2 positions a sample", narrow,
                                 r"standby joint_trajectory needs 2 or more samples, each "
                                 r"of 6 positions")]
        return super().odd(key)

    def after(self, h: Harness) -> None:
        backwards = h.wait_for("wavegrasp/gate/decision", lambda d: d.plan_id == "backwards")
        assert not backwards.go and backwards.reason.startswith("bad plan"), backwards.reason
        self.feed(h, 31, 50)
        d = self.decide(h, self.plan(5.0, 5.3, 6.0, "b"), now_s=5.05)
        assert d.go, d.reason
        assert d.mean_error_m is not None and d.mean_error_m < 0.001
        for token in self.tokens:
            token.undeclare()


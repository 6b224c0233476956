"""The decision gate: crafted message sequences through ``Gate``, and the service on a bus."""

from __future__ import annotations

import math
import re
import time

import numpy as np
import pytest

from wavegrasp.arm import ArmModel
from wavegrasp.gate.decision import Gate, GateConfig, time_average
from wavegrasp.gate.main import GateService, GateSettings
from wavegrasp.recording_io.ros_msgs import decode_joint_trajectory
from wavegrasp.runtime.bus import JSON, Bus, Delivery
from wavegrasp.schemas import (
    Clock,
    GateDecision,
    GraspOutcome,
    GraspPlan,
    Header,
    Hop,
    JointSample,
    MotionPrediction,
    ObjectObservation,
    Pose,
    PredictionSample,
    Vec3,
)

from conftest import wait_until

T0 = 1_000 * 10**9  # recording clock origin, ns
ALIVE = {"perception", "predictor", "planner"}
PERIOD_S = 4.0


def ns(t_s: float) -> int:
    return T0 + round(t_s * 1e9)


def motion(t_s: float) -> np.ndarray:
    """The object's true centroid (m): a wave-driven orbit."""
    w = 2 * math.pi / PERIOD_S
    return np.array([0.6 + 0.05 * math.sin(w * t_s), 0.1, -0.4 + 0.03 * math.sin(w * t_s + 1)])


def prediction(made_s: float, offset=(0.0, 0.0, 0.0)) -> MotionPrediction:
    """The same motion from ``made_s`` to 1.5 s ahead, every 50 ms, shifted by ``offset`` (m)."""
    samples = []
    for k in range(31):
        t = made_s + 0.05 * k
        p = motion(t) + offset
        samples.append(PredictionSample(t_ns=ns(t), x=p[0], y=p[1], z=p[2], sigma=0.005))
    return MotionPrediction(header=Header(stamp_ns=ns(made_s)), model="test", period_s=PERIOD_S,
                            samples=samples)


def observation(t_s: float, noise: np.ndarray, jump_m: float = 0.0) -> ObjectObservation:
    p = motion(t_s) + noise + [jump_m, 0.0, 0.0]
    return ObjectObservation(header=Header(stamp_ns=ns(t_s)), centroid=Vec3(x=p[0], y=p[1], z=p[2]),
                             points_used=500, quality=1.0, sigma_m=0.001)


def feed(gate: Gate, start_s: float = 0.0, end_s: float = 3.0, offset=(0.0, 0.0, 0.0),
         jump_from_s: float = math.inf, seed: int = 0) -> None:
    """Observations every 0.1 s (1 mm noise), each followed by a prediction made at its stamp."""
    rng = np.random.default_rng(seed)
    for i in range(round(start_s * 10), round(end_s * 10) + 1):
        t = i / 10
        jump = 0.05 if t >= jump_from_s else 0.0
        gate.on_observation(observation(t, rng.normal(0, 0.001, 3), jump))
        gate.on_prediction(prediction(t, offset))


def plan(made_s: float, start_s: float, grasp_s: float, plan_id: str = "p1") -> GraspPlan:
    """A plan for our arm, holding its home pose from its start to the grasp."""
    g, arm = motion(grasp_s), ArmModel.load()
    return GraspPlan(header=Header(stamp_ns=ns(made_s), trace=[Hop(service="source", recv_ns=1)]),
                     plan_id=plan_id, t_start_ns=ns(start_s), t_grasp_ns=ns(grasp_s),
                     grasp=Pose(position=Vec3(x=g[0], y=g[1], z=g[2])),
                     approach=Vec3(x=0, y=0, z=-1), joint_names=list(arm.joint_names),
                     joint_trajectory=[JointSample(t_ns=ns(t), positions=list(arm.q_home))
                                       for t in sorted({start_s, grasp_s})])


def decide(gate: Gate, p: GraspPlan, now_s: float, alive=ALIVE,
           latency_s: float = 0.02) -> GateDecision:
    return gate.decide(p, ns(now_s), set(alive), latency_s)


def test_clean_sequence_goes() -> None:
    gate = Gate()
    feed(gate)
    d = decide(gate, plan(3.0, 3.3, 4.0), now_s=3.05)
    assert d.go, d.reason
    assert d.mean_error_m < 0.003 and d.threshold_m == 0.010 and d.window_s == 2.0
    assert d.reason.startswith("go: error") and d.failed == [] and d.matches == 20
    assert all(abs(e.lead_s - 0.2) < 1e-9 for e in gate.errors)  # most recent at >= 0.2 s


def test_error_above_epsilon_is_no_go_naming_the_error() -> None:
    gate = Gate()
    feed(gate, offset=(0.02, 0.0, 0.0))
    d = decide(gate, plan(3.0, 3.3, 4.0), now_s=3.05)
    assert not d.go and d.failed == ["error"]
    assert d.reason.startswith("error 2") and d.reason.endswith("mm > 10.0 mm")
    assert 0.018 < d.mean_error_m < 0.022


def test_stale_inputs_are_no_go() -> None:
    gate = Gate()
    feed(gate)
    d = decide(gate, plan(3.0, 5.0, 5.5), now_s=4.0)
    assert not d.go and set(d.failed) == {"stale"}
    assert "stale observation: 1.00 s old" in d.reason
    assert "stale prediction: 1.00 s old" in d.reason
    d = decide(gate, plan(2.0, 3.5, 4.0), now_s=3.05)  # the plan's prediction only
    assert not d.go and d.reason == "stale prediction: 1.05 s old"
    assert "stale observation: none yet" in decide(Gate(), plan(0, 1, 2), now_s=0).reason


def test_plan_too_close_to_start_is_no_go() -> None:
    gate = Gate()
    feed(gate)
    d = decide(gate, plan(3.0, 3.08, 4.0), now_s=3.05, latency_s=0.012)
    assert not d.go and d.reason == "cannot start on time: 30 ms left, 62 ms needed"


def test_dead_upstream_is_no_go_naming_it() -> None:
    gate = Gate()
    feed(gate)
    d = decide(gate, plan(3.0, 3.3, 4.0), now_s=3.05, alive={"perception", "planner", "sim"})
    assert not d.go and d.reason == "upstream not alive: predictor"


def test_abrupt_change_after_the_plans_prediction_is_no_go() -> None:
    gate = Gate()
    feed(gate, jump_from_s=2.95)  # the object jumps 5 cm at the last frame, 3.0 s
    d = decide(gate, plan(2.9, 3.3, 4.0), now_s=3.05)
    assert not d.go and d.failed == ["abrupt"], d.reason
    assert re.fullmatch(r"abrupt change: e 5\d mm vs mean [12] mm", d.reason), d.reason
    assert d.mean_error_m < 0.010  # the mean alone would have let it go
    # a jump before the plan's prediction is in the mean error, not an abrupt change
    gate = Gate()
    feed(gate, end_s=2.0)
    feed(gate, start_s=2.1, end_s=3.0, jump_from_s=2.1)
    d = decide(gate, plan(3.0, 3.3, 4.0), now_s=3.05)
    assert not d.go and d.failed == ["error"]


def test_too_few_matches_is_warming_up() -> None:
    gate = Gate()
    feed(gate, end_s=0.8)  # observations at 0.2 .. 0.8 s have a prediction 0.2 s old
    d = decide(gate, plan(0.8, 1.1, 1.8), now_s=0.85)
    assert not d.go and d.reason == "warming up: 7 of 10 errors"


def test_a_slow_camera_needs_fewer_matches_but_still_a_full_window() -> None:
    """A 5 Hz camera gives 10 frames in the 2 s window; with a quarter of them lacking a
    centroid the window never holds min_matches (10) errors. The rate sets the need instead,
    and a window not yet full still waits."""
    gate, rng = Gate(), np.random.default_rng(0)
    for i in range(21):  # 0 .. 4 s every 0.2 s
        t = i / 5
        obs = observation(t, rng.normal(0, 0.001, 3))
        if i % 4 == 3:
            obs = obs.model_copy(update={"centroid": None})
        gate.on_observation(obs)
        gate.on_prediction(prediction(t))
        if t == 1.2:
            early = decide(gate, plan(1.2, 1.5, 2.2), now_s=1.25)
    assert not early.go and early.failed == ["warming up"], early.reason
    d = decide(gate, plan(4.0, 4.3, 5.0), now_s=4.05)
    assert d.go and d.matches < 10, d.reason
    assert gate.required_matches() == 6


def test_perception_reporting_few_frames_fills_the_window_from_just_before_it() -> None:
    """A 10 Hz camera, perception reporting 4 frames in 10 (a box too uncertain to report in
    the others): every 2 s window holds 8 errors, never min_matches (10). The latest errors
    before the window make up the number; those older than two windows never do."""
    gate, rng = Gate(), np.random.default_rng(0)
    for i in range(41):  # 0 .. 4 s every 0.1 s
        t = i / 10
        obs = observation(t, rng.normal(0, 0.001, 3))
        if i % 10 >= 4:
            obs = obs.model_copy(update={"centroid": None})
        gate.on_observation(obs)
        gate.on_prediction(prediction(t))
    assert gate.required_matches() == 10
    assert len([e for e in gate.errors if e.t_ns >= ns(2.05)]) < 10
    d = decide(gate, plan(4.0, 4.3, 5.0), now_s=4.05)
    assert d.go and d.matches == 10, d.reason
    for i in range(41, 61):  # 2 s more with no centroid at all: 7 errors within 4 s
        gate.on_observation(observation(i / 10, np.zeros(3)).model_copy(
            update={"centroid": None}))
        gate.on_prediction(prediction(i / 10))
    d = decide(gate, plan(6.0, 6.3, 7.0), now_s=6.05)
    assert not d.go and "warming up" in d.failed, d.reason


def test_one_plan_executes_at_a_time() -> None:
    gate = Gate()
    feed(gate)
    assert decide(gate, plan(3.0, 3.3, 4.0, "a"), now_s=3.05).go
    d = decide(gate, plan(3.0, 3.4, 4.1, "b"), now_s=3.06)
    assert not d.go and d.reason == "another plan executing: a"
    assert not decide(gate, plan(3.0, 3.3, 4.0, "a"), now_s=3.07).go  # at most one go per plan
    assert gate.on_outcome("a")
    assert decide(gate, plan(3.0, 3.4, 4.1, "b"), now_s=3.08).go
    feed(gate, start_s=3.1, end_s=5.7)  # b runs until 4.1 + 1.5 s hold
    assert "another plan executing: b" in decide(gate, plan(5.5, 5.8, 6.5, "c"), 5.55).reason
    assert decide(gate, plan(5.7, 6.0, 6.7, "c"), now_s=5.75).go


def test_bad_input_raises_value_errors_naming_the_problem() -> None:
    gate = Gate()
    pred = prediction(0.0)
    pred.samples.reverse()
    with pytest.raises(ValueError, match="not strictly increasing"):
        gate.on_prediction(pred)
    with pytest.raises(ValueError, match="has 0 samples, need at least 2"):
        gate.on_prediction(MotionPrediction(header=Header(), model="m", period_s=1, samples=[]))
    with pytest.raises(ValueError, match="finite number"):  # the message refuses NaN itself
        observation(0.0, np.array([math.nan, 0, 0]))
    nan = ObjectObservation.model_construct(header=Header(), centroid=Vec3.model_construct(
        x=math.nan, y=0.0, z=0.0))
    with pytest.raises(ValueError, match="centroid not finite"):
        gate.on_observation(nan)
    feed(gate, end_s=0.5)
    with pytest.raises(ValueError, match=r"duplicate: stamp \d+ <= last"):
        gate.on_observation(observation(0.5, np.zeros(3)))
    with pytest.raises(ValueError, match=r"out of order: stamp \d+ <= last"):
        gate.on_observation(observation(0.3, np.zeros(3)))
    with pytest.raises(ValueError, match="t_grasp_ns before t_start_ns"):
        decide(gate, plan(0.0, 1.0, 0.5), now_s=0.0)
    assert gate.on_observation(ObjectObservation(header=Header(), reason="empty cloud")) is None


def test_mean_error_is_a_trapezoid_time_average() -> None:
    assert time_average([0, 1, 3], [0.0, 2.0, 2.0]) == pytest.approx(5 / 3)
    assert time_average([5], [0.004]) == 0.004
    with pytest.raises(ValueError):
        time_average([], [])
    gate = Gate(GateConfig(window_s=1.0))
    feed(gate, offset=(0.0, 0.0, 0.01))
    assert gate.mean_error(ns(3.0)) == pytest.approx(0.01, abs=0.002)
    assert len(gate.window(ns(3.0))) == 11 and gate.mean_error(ns(10.0)) is None


def test_settings_from_env() -> None:
    env = {"WAVEGRASP_EPSILON_M": "0.02", "WAVEGRASP_REQUIRED_SERVICES": "perception,predictor"}
    cfg = GateSettings.from_env("gate", env=env, window_s=1.5).gate_config()
    assert cfg.epsilon_m == 0.02 and cfg.window_s == 1.5
    assert cfg.required_services == ["perception", "predictor"] and cfg.min_matches == 10
    with pytest.raises(ValueError, match="WAVEGRASP_EPSILON_M"):
        GateSettings.from_env("gate", env={"WAVEGRASP_EPSILON_M": "-1"})


def test_gate_service_on_an_isolated_bus() -> None:
    settings = GateSettings(service="gate", zenoh_mode="peer", zenoh_connect=[], zenoh_listen=[])
    bus = Bus(settings)
    try:
        service = GateService(settings, bus=bus)
        tokens = [bus.session.liveliness().declare_token(f"wavegrasp/health/{name}")
                  for name in ("perception", "predictor")]  # the planner is not up yet
        routes = {key: i for i, key in enumerate(bus.subscriptions)}
        seen: list[GateDecision] = []
        bus.subscribe("wavegrasp/gate/decision", lambda m, d: seen.append(m), GateDecision)
        commanded: list[tuple[str, tuple]] = []  # what the arm's controllers were sent
        for key in (settings.arm_trajectory_key, settings.jaw_trajectory_key):
            bus.subscribe(key, lambda d: commanded.append(
                (d.key, decode_joint_trajectory(d.payload))))

        def send(key: str, msg) -> bool:
            payload = msg.model_dump_json().encode()
            d = Delivery(key, payload, f"{JSON};{type(msg).__name__}", None, time.time_ns(),
                         routes[key])
            return bus.dispatch(d)

        def decisions(n: int) -> list[GateDecision]:
            def arrived() -> bool:
                while not bus.inbox.empty():
                    bus.dispatch(bus.inbox.get())
                return len(seen) >= n
            assert wait_until(arrived, timeout=5)
            return seen

        assert send("wavegrasp/clock", Clock(header=Header(stamp_ns=ns(3.05)), rate=0.0))
        rng = np.random.default_rng(1)
        for i in range(31):
            assert send("wavegrasp/perception/object", observation(i / 10, rng.normal(0, 1e-3, 3)))
            assert send("wavegrasp/predictor/prediction", prediction(i / 10))
        p = plan(3.0, 3.3, 4.0, "a")
        p.header.trace = [Hop(service="source", recv_ns=time.time_ns())]
        assert wait_until(lambda: bus.alive_now() >= {"perception", "predictor"}, timeout=5)
        assert send("wavegrasp/planner/plan", p)
        first = decisions(1)[0]
        assert not first.go and first.reason == "upstream not alive: planner"
        tokens.append(bus.session.liveliness().declare_token("wavegrasp/health/planner"))
        assert wait_until(lambda: "planner" in bus.alive_now(), timeout=5)
        assert send("wavegrasp/planner/plan", p)
        assert send("wavegrasp/planner/plan", plan(3.0, 3.0, 2.0, "bad"))
        d, bad = decisions(3)[1:]
        assert d.go, d.reason
        assert [h.service for h in d.header.trace] == ["source", "gate"]
        assert d.header.stamp_ns == ns(3.0) and d.header.trace[-1].sent_ns > 0
        assert not bad.go and bad.reason.startswith("bad plan: plan bad: t_grasp_ns before")
        # The go's paths went to the arm's and the jaw's controllers.
        assert [key for key, _ in commanded] == [settings.arm_trajectory_key,
                                                 settings.jaw_trajectory_key]
        (arm_names, times, _q, _qd), (jaw_names, jaw_times, _, _) = (x for _, x in commanded)
        assert arm_names == list(service.commander.names)
        assert times[0] == pytest.approx(ns(3.3) * 1e-9)
        assert times[-1] >= ns(4.0) * 1e-9 + settings.hold_s - 1e-6  # held, then back
        assert jaw_names == list(service.commander.jaw_names) and len(jaw_times) >= 4
        outcome = GraspOutcome(header=Header(), plan_id="a", trial=0, attempt=0, success=True)
        assert send("wavegrasp/sim/outcome", outcome)
        assert not service.gate.executing
        pathless = plan(3.1, 3.4, 4.1, "pathless").model_copy(update={"joint_trajectory": []})
        assert send("wavegrasp/planner/plan", pathless)  # cannot be followed: no go
        refused = decisions(4)[3]
        assert not refused.go and refused.reason == "bad plan: plan pathless: no joint_trajectory"
        assert not service.gate.executing and len(commanded) == 2
        assert not send("wavegrasp/predictor/prediction", MotionPrediction(
            header=Header(), model="m", period_s=1.0, samples=[]))  # counted as bad, not fatal
        assert bus.bad["wavegrasp/predictor/prediction"] == 1
        assert service.counters["go"] == 1 and service.counters["no-go"] == 3
        assert service.counters["no-go: upstream"] == 1
        assert service.counters["no-go: bad plan"] == 2
        assert service.counters["errors scored"] == 29
        tokens.pop().undeclare()  # the planner goes away: the gate sees it gone
        assert wait_until(lambda: "planner" not in bus.alive_now(), timeout=5)
        for token in tokens:
            token.undeclare()
    finally:
        bus.close()


def test_closed_loop_watch_aborts_an_executing_plan_past_its_limits() -> None:
    """While a plan executes, the gate aborts it when the newest prediction puts the object
    far from the grasp point, and when its predictions go stale; never in open loop."""
    gate = Gate()
    feed(gate)
    assert decide(gate, plan(3.0, 3.3, 4.5), now_s=3.05).go
    assert gate.watch(ns(3.05)) is None  # all well
    # Updates are approved while it executes; a plan not executing is not updated.
    update = plan(3.1, 3.2, 4.5, plan_id="p1-u").model_copy(update={"update_of": "p1"})
    assert decide(gate, update, now_s=3.1).go
    stray = update.model_copy(update={"update_of": "p9"})
    assert decide(gate, stray, now_s=3.1).failed == ["not executing"]
    # The object carried 5 cm away: the newest prediction says it will be there at the grasp.
    feed(gate, 3.1, 3.2, offset=(0.0, 0.05, 0.0))
    plan_id, kind, reason, value, limit = gate.watch(ns(3.2))
    assert (plan_id, kind) == ("p1", "prediction moved") and value == pytest.approx(0.05, 0.05)
    # its own sigma there: 5 mm (test prediction), the limit 3 cm + 2 sigma
    assert "50 mm from the grasp point (limit 40 mm)" in reason and limit == pytest.approx(0.04)


def test_closed_loop_watch_aborts_when_predictions_go_stale() -> None:
    gate = Gate()
    feed(gate)
    assert decide(gate, plan(3.0, 3.3, 4.5), now_s=3.05).go
    for k in range(1, 8):  # the camera goes on, the predictor has gone silent
        gate.on_observation(observation(3.0 + k / 10, np.zeros(3)))
    _, kind, reason, value, _ = gate.watch(ns(3.7))
    assert kind == "stale prediction" and value == pytest.approx(0.7)
    assert reason == "stale prediction: 0.70 s old"
    # After the grasp time there is nothing left to abort.
    assert gate.watch(ns(4.6)) is None


def test_open_loop_never_aborts_nor_updates() -> None:
    gate = Gate(GateConfig(execution="open"))
    feed(gate)
    assert decide(gate, plan(3.0, 3.3, 4.5), now_s=3.05).go
    feed(gate, 3.1, 3.2, offset=(0.0, 0.05, 0.0))
    assert gate.watch(ns(3.2)) is None
    update = plan(3.1, 3.2, 4.5, plan_id="p1-u").model_copy(update={"update_of": "p1"})
    assert "open loop" in decide(gate, update, now_s=3.1).failed


def test_closed_loop_watch_aborts_an_update_heading_into_the_object() -> None:
    """An update the planner found touching the object before its final move (its
    t_contact_ns) is approved while the contact is far off, and aborted once it is within
    abort_contact_s; a later update that keeps clear lifts it."""
    gate = Gate()
    feed(gate)
    assert decide(gate, plan(3.0, 3.3, 4.5), now_s=3.05).go
    update = plan(3.1, 3.2, 4.5, plan_id="p1-u").model_copy(
        update={"update_of": "p1", "t_contact_ns": ns(4.3)})
    assert decide(gate, update, now_s=3.1).go
    assert gate.watch(ns(3.2)) is None  # 1.1 s ahead: the forecast may yet clear it
    plan_id, kind, reason, value, limit = gate.watch(ns(3.4))
    assert (plan_id, kind) == ("p1", "contact ahead") and value == pytest.approx(0.9)
    assert reason == "the arm would touch the object in 0.90 s (limit 1.00 s)" and limit == 1.0
    clear = plan(3.3, 3.5, 4.5, plan_id="p1-v").model_copy(update={"update_of": "p1"})
    assert decide(gate, clear, now_s=3.4).go
    assert gate.watch(ns(3.4)) is None

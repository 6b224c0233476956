"""Closed-loop execution: an approved plan moved to where the newest prediction puts the
object, spliced from the arm's state within its limits."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from wavegrasp.arm import ArmModel
from wavegrasp.gate.command import Commander
from wavegrasp.gate.decision import Gate
from wavegrasp.planner.approach import PredictedPath
from wavegrasp.planner.main import to_message
from wavegrasp.planner.plan import Plan, PlannerConfig, plan_grasp
from wavegrasp.planner.update import state_at, update_plan
from wavegrasp.schemas import (
    Header,
    MotionPrediction,
    ObjectObservation,
    PredictionSample,
    Vec3,
)
from wavegrasp.sim.executor import Attempt, Executor, Result
from wavegrasp.sim.world import SimWorld

from test_planner import BODY, T_world_base, arm, prediction  # noqa: F401 (fixtures)
from test_sim import CAN, UPRIGHT, plan_for, swing
from test_sim import NOW as SIM_NOW

NOW = 10.0


@pytest.fixture(scope="module")
def approved(arm: ArmModel, T_world_base: np.ndarray) -> Plan:  # noqa: F811
    plan = plan_grasp(prediction(NOW), NOW, arm, T_world_base, arm.q_home, BODY,
                      PlannerConfig())
    assert isinstance(plan, Plan), dict(plan)
    return plan


def moved(by: tuple[float, float, float], now: float):
    path = prediction(now)
    return replace(path, positions=path.positions + np.array(by))


@pytest.mark.parametrize("during", ["wait", "move to P_init", "approach"])
def test_an_update_moves_the_grasp_and_splices_from_the_arms_state_within_limits(
        arm: ArmModel, T_world_base: np.ndarray, approved: Plan, during: str) -> None:  # noqa: F811
    cfg = PlannerConfig()
    now = {"wait": approved.t_start, "move to P_init": approved.move_s[0] + 0.05,
           "approach": approved.knots[0] + 0.05}[during]
    if now + cfg.update_delay_s + cfg.splice_s > approved.t_grasp:
        pytest.skip("the approach is too short to update during it")
    shift = np.array([0.0, 0.0, 0.03])  # the object 3 cm higher than predicted at approval
    new = update_plan(approved, moved(shift, now), now, arm, T_world_base, BODY, cfg)
    assert isinstance(new, Plan), new
    # The grasp moved with the object, at the same time, in the same orientation.
    assert new.t_grasp == approved.t_grasp
    np.testing.assert_allclose(new.grasp_T_world[:3, 3], approved.grasp_T_world[:3, 3] + shift,
                               atol=2e-4)  # the same swing, sampled from another time
    np.testing.assert_allclose(new.grasp_T_world[:3, :3], approved.grasp_T_world[:3, :3])
    assert np.linalg.norm(new.tool[-1] - new.grasp_T_world[:3, 3]) < 0.002
    # Nothing changes before it takes over; from there on it starts from the arm's state.
    take = now + cfg.update_delay_s
    before = approved.times < take - cfg.sample_dt_s / 2
    np.testing.assert_allclose(new.q[: before.sum()], approved.q[before])
    np.testing.assert_allclose(new.times[: before.sum()], approved.times[before])
    for a, b in zip(state_at(approved.times, approved.q, approved.qd, take)[:2],
                    state_at(new.times, new.q, new.qd, take)[:2], strict=True):
        np.testing.assert_allclose(a, b, atol=2e-3)
    # Within the arm's limits all the way; every sample a time of its own, in whole ns too.
    assert np.all(np.diff(new.times) > cfg.sample_dt_s * 1e-3)
    assert np.all(np.abs(new.qd) <= arm.max_velocity * (1 + 1e-6))
    acc = np.diff(new.qd, axis=0) / np.diff(new.times)[:, None]
    assert np.all(np.abs(acc) <= arm.max_acceleration * 1.1)


def test_an_update_refuses_what_it_cannot_do(arm: ArmModel, T_world_base: np.ndarray,  # noqa: F811
                                             approved: Plan) -> None:
    cfg = PlannerConfig()
    now = approved.move_s[0]
    assert update_plan(approved, moved((0.0, 0.0, 0.0), now), now, arm, T_world_base, BODY,
                       cfg) == "unchanged"
    assert update_plan(approved, moved((0.0, 0.0, 0.2), now), now, arm, T_world_base, BODY,
                       cfg) == "moved too far"
    late = approved.t_grasp - 0.05
    assert update_plan(approved, moved((0.0, 0.0, 0.01), late), late, arm, T_world_base, BODY,
                       cfg) == "too late"


def ns(t: float) -> int:
    return int(round(t * 1e9))


def forecast(path: PredictedPath, seq: int = 0) -> MotionPrediction:
    """``path`` as the predictor sends it, made at its first time."""
    return MotionPrediction(
        header=Header(seq=seq, stamp_ns=ns(path.times_s[0])), model="test",
        period_s=path.period_s, samples=[
            PredictionSample(t_ns=ns(t), x=p[0], y=p[1], z=p[2], sigma=s)
            for t, p, s in zip(path.times_s, path.positions, path.sigma, strict=True)])


def seen(t: float, p: np.ndarray) -> ObjectObservation:
    return ObjectObservation(header=Header(stamp_ns=ns(t)),
                             centroid=Vec3(x=p[0], y=p[1], z=p[2]), points_used=500,
                             quality=1.0, sigma_m=0.001)


def follow(arm: ArmModel, T_world_base: np.ndarray, truth, closed: bool,  # noqa: F811
           abort_at: float | None = None, gate: Gate | None = None, predict=None
           ) -> tuple[Result, set[str]]:
    """One attempt in PyBullet planned on the swing as it was (test_sim's can) at test_sim's
    NOW, the object moving as ``truth``; ``closed``: every 0.1 s the plan is moved to a
    prediction of the object as it moves now (``predict(now, t)``, by default ``truth``
    from then on, what a good predictor would say) and spliced in, as the planner and the
    sim do; ``abort_at``: the gate aborts
    then; ``gate``: a gate that approved the plan sees the object and the predictions every
    0.1 s, approves each update and watches, as the gate service does, and the attempt is
    aborted when it says. Returns the result and the arm's links that touched the object
    before the attempt was judged (and, once aborted, on its way back to standby)."""
    plan, path = plan_for(arm, T_world_base)
    attempt = Attempt("p", plan.times, plan.q, plan.qd, plan.t_grasp, plan.grasp_T_world[:3, 3],
                      plan.t_final, plan.jaw_preshape_m, plan.t_close,
                      (path.times_s, path.positions), SIM_NOW)
    world = SimWorld(arm, T_world_base, CAN)
    touched: set[str] = set()
    cfg = PlannerConfig()
    predict = predict or (lambda _now, t: truth(t))
    try:
        world.place_object(truth(SIM_NOW), UPRIGHT)
        world.step_to(SIM_NOW)
        executor, commander = Executor(world), Commander(arm)
        for commanded in commander.grasp(attempt):  # as the gate commands it
            executor.follow(commanded)
        executor.start(attempt)
        result, found = None, None
        for k, t in enumerate(SIM_NOW + np.arange(1, 600) * 0.01):
            if closed and k % 10 == 0 and executor.attempt is not None:
                ahead = t + np.arange(41) * 0.1
                now_path = replace(path, times_s=ahead,
                                   positions=np.array([predict(t, x) for x in ahead]))
                moved_plan = update_plan(plan, now_path, t, arm, T_world_base, BODY, cfg)
                if gate is not None:
                    gate.on_observation(seen(t, truth(t)))
                    gate.on_prediction(forecast(now_path, k))
                    if isinstance(moved_plan, Plan) and not gate.decide_update(to_message(
                            moved_plan, forecast(now_path, k), ns(t), arm, "planner",
                            update_of="p", since=t + cfg.update_delay_s), ns(t), 0.02).go:
                        moved_plan = "refused"
                    found = gate.watch(ns(t))
                    if found is not None:
                        abort_at = t
                        gate.on_outcome(found[0])
                if isinstance(moved_plan, Plan):
                    plan = moved_plan
                    keep = plan.times >= t + cfg.update_delay_s - 1e-9
                    update = Attempt("u", plan.times[keep], plan.q[keep], plan.qd[keep],
                                     plan.t_grasp, plan.grasp_T_world[:3, 3], plan.t_final,
                                     plan.jaw_preshape_m, plan.t_close)
                    for commanded in commander.grasp(update, update=True):
                        executor.follow(commanded)
                    executor.splice(update, "p")
            if abort_at is not None and t >= abort_at and executor.attempt is not None:
                for commanded in commander.abort(t):
                    executor.follow(commanded)
                result = executor.abort("test" if found is None else found[1])
            judged = executor.advance(t, truth(t), UPRIGHT)
            result = result or judged
            touched |= {world.link_names[i] for i in world.contacts()}
            if result is not None and not executor.busy:
                return result, touched
            if result is not None and not result.aborted:
                return result, touched
        raise AssertionError("the attempt was never judged or never got back")
    finally:
        world.close()


def carried(by: tuple[float, float, float], after_s: float):
    """test_sim's swing, carried ``by`` metres over 0.3 s from ``after_s`` after NOW on."""
    def truth(t: float) -> np.ndarray:
        return swing(t) + np.array(by) * min(max(t - SIM_NOW - after_s, 0.0) / 0.3, 1.0)
    return truth


def test_a_target_that_moves_3_cm_after_approval_is_still_grasped(
        arm: ArmModel, T_world_base: np.ndarray) -> None:  # noqa: F811
    plan, _ = plan_for(arm, T_world_base)
    across = plan.grasp_T_world[:3, 0]  # the way the jaw closes: 3 cm is past a finger
    truth = carried(tuple(0.03 * across), 0.4)  # 0.4 s after approval
    result, _ = follow(arm, T_world_base, truth, closed=True)
    assert result.success, result
    # Open loop, as the paper executes, the same attempt misses it.
    result, _ = follow(arm, T_world_base, truth, closed=False)
    assert not result.success, result


def test_an_abort_during_the_approach_retreats_without_touching_the_object(
        arm: ArmModel, T_world_base: np.ndarray) -> None:  # noqa: F811
    plan, _ = plan_for(arm, T_world_base)
    during = (plan.knots[0] + plan.t_final) / 2  # well into the approach
    result, touched = follow(arm, T_world_base, swing, closed=False, abort_at=during)
    assert result.aborted and not result.success and result.failure is None, result
    assert result.evidence["reason"] == "test" and result.evidence["before_grasp_s"] > 0
    assert not touched, touched


def approving_gate(arm: ArmModel, plan: Plan) -> Gate:  # noqa: F811
    """A gate that has seen the swing tracked to a millimetre for 3 s and approved ``plan``
    (made at test_sim's NOW, as ``p``)."""
    gate = Gate()
    for k, t in enumerate(SIM_NOW - 3.0 + np.arange(31) * 0.1):
        ahead = t + np.arange(41) * 0.1
        gate.on_observation(seen(t, swing(t)))
        gate.on_prediction(forecast(PredictedPath(ahead, np.array([swing(x) for x in ahead]),
                                                  np.full(41, 0.002), 4.0), k))
    sent = to_message(plan, gate_prediction(gate), ns(SIM_NOW), arm, "planner")
    decision = gate.decide(sent.model_copy(update={"plan_id": "p"}), ns(SIM_NOW),
                           {"perception", "predictor", "planner"}, 0.02)
    assert decision.go, decision.reason
    return gate


def gate_prediction(gate: Gate) -> MotionPrediction:
    return MotionPrediction(header=Header(seq=30, stamp_ns=ns(SIM_NOW)), model="test",
                            period_s=4.0, samples=[])


def test_an_abrupt_change_during_the_approach_is_aborted_by_the_gate_and_the_arm_backs_away(
        arm: ArmModel, T_world_base: np.ndarray) -> None:  # noqa: F811
    """The chain as the services run it: the object jumps 6 cm away along the approach
    while the arm is on its way in; the planner cannot follow that far, the gate's watch
    aborts, and the arm backs out to standby without touching the object."""
    plan, _ = plan_for(arm, T_world_base)
    during = (plan.knots[0] + plan.t_final) / 2
    jump = 0.06 * plan.approach / np.linalg.norm(plan.approach)

    def truth(t: float) -> np.ndarray:
        return swing(t) + (jump if t >= during else 0.0)

    def predict(now: float, t: float) -> np.ndarray:  # the jump is seen, not foreseen
        return swing(t) + truth(now) - swing(now)

    result, touched = follow(arm, T_world_base, truth, closed=True,
                             gate=approving_gate(arm, plan), predict=predict)
    assert result.aborted and not result.success, result
    assert result.evidence["reason"] in ("prediction moved", "tracking error"), result
    # at the first frame after the jump (the world steps 10 ms; frames come every 0.1 s)
    assert 0 < result.evidence["before_grasp_s"] <= plan.t_grasp - during + 0.01, result
    assert not touched, touched


def test_closed_loop_plans_where_only_the_forecast_of_its_last_corrections_is_trusted(
        arm: ArmModel, T_world_base: np.ndarray) -> None:  # noqa: F811
    """An irregular sea's forecast: sure half a second ahead, 10 cm unsure from 1 s on. Open
    loop trusts no grasp time; closed loop plans, its grasp corrected on the way."""
    path = prediction(NOW)
    lead = path.times_s - NOW
    unsure = replace(path, sigma=np.where(lead <= 0.6, 0.01, 0.10))
    assert plan_grasp(unsure, NOW, arm, T_world_base, arm.q_home, BODY,
                      PlannerConfig()) == {"prediction too uncertain": 1}
    plan = plan_grasp(unsure, NOW, arm, T_world_base, arm.q_home, BODY,
                      PlannerConfig(closed_loop=True))
    assert isinstance(plan, Plan), plan
    # Unsure half a second ahead too: nothing to correct towards.
    blind = replace(path, sigma=np.full(len(lead), 0.10))
    assert plan_grasp(blind, NOW, arm, T_world_base, arm.q_home, BODY,
                      PlannerConfig(closed_loop=True)) == {"prediction too uncertain": 1}


"""Closed-loop execution: an approved plan moved to where the newest prediction puts the
object, spliced from the arm's state within its limits."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from test_planner import BODY, T_world_base, arm, prediction  # noqa: F401 (fixtures)

from wavegrasp.arm import ArmModel
from wavegrasp.planner.plan import Plan, PlannerConfig, plan_grasp
from wavegrasp.planner.update import state_at, update_plan

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


@pytest.mark.parametrize("during", ["move to P_init", "approach"])
def test_an_update_moves_the_grasp_and_splices_from_the_arms_state_within_limits(
        arm: ArmModel, T_world_base: np.ndarray, approved: Plan, during: str) -> None:  # noqa: F811
    cfg = PlannerConfig()
    now = approved.move_s[0] + 0.05 if during == "move to P_init" else approved.knots[0] + 0.05
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
    # Within the arm's limits all the way.
    assert np.all(np.diff(new.times) > 0)
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

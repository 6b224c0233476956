"""The commander turns approvals, updates, aborts and standby moves into the paths a
ros2_control arm's joint trajectory controllers follow, and the paths travel as
``trajectory_msgs/msg/JointTrajectory``."""

from __future__ import annotations

import numpy as np
import pytest

from wavegrasp.arm import ArmModel
from wavegrasp.arm.motion import Attempt, JointPath
from wavegrasp.gate.command import CommandConfig, Commander
from wavegrasp.recording_io.ros_msgs import decode_joint_trajectory, encode_joint_trajectory

T0 = 20.0


@pytest.fixture(scope="module")
def arm() -> ArmModel:
    return ArmModel.load()


def attempt(arm: ArmModel, t0: float = T0, plan_id: str = "p") -> Attempt:
    """A 2 s plan from home to home + 0.3 rad on every joint, grasping at its end."""
    times = t0 + np.linspace(0.0, 2.0, 21)
    s = (times - t0) / 2.0
    q = arm.q_home + 0.3 * s[:, None] * np.ones(len(arm.joint_names))
    qd = np.gradient(q, times, axis=0)
    qd[-1] = 0.0
    return Attempt(plan_id, times, q, qd, t0 + 2.0, np.zeros(3), t0 + 1.5, 0.08, t0 + 1.8,
                   standby=arm.q_home + 0.1)


def opening(commander: Commander, jaw: JointPath, t_s: float) -> float:
    return float(np.sum(jaw.heading(t_s)))


def test_an_approved_plan_is_followed_held_then_returned_with_the_jaw_timed(arm) -> None:
    commander = Commander(arm, CommandConfig(hold_s=1.6))
    a = attempt(arm)
    path, jaw = commander.grasp(a)
    assert path.names == list(arm.joint_names) and jaw.names == list(arm.jaw_joints)
    np.testing.assert_allclose(path.q[:21], a.q)  # the plan's own samples first
    q, qd = path.at(a.t_grasp + 1.0)  # held after the grasp time
    np.testing.assert_allclose(q, a.q[-1])
    np.testing.assert_allclose(qd, 0.0, atol=1e-9)
    assert path.at(a.t_grasp + 1.59)[0] == pytest.approx(a.q[-1])
    assert path.end_s > a.t_grasp + 1.6  # then back to its standby, at rest
    np.testing.assert_allclose(path.q[-1], a.standby, atol=1e-9)
    np.testing.assert_allclose(path.qd[-1], 0.0, atol=1e-9)
    assert np.abs(np.diff(path.q, axis=0)).max() < 0.05  # no jump on the way
    wide = arm.jaw_max_opening_m
    assert opening(commander, jaw, T0 + 0.5) == pytest.approx(wide)  # open for the approach
    assert opening(commander, jaw, a.final_from + 0.01) == pytest.approx(0.08)  # narrowed
    assert opening(commander, jaw, a.t_close + 0.01) == pytest.approx(0.0)  # closing
    assert opening(commander, jaw, a.t_grasp + 1.0) == pytest.approx(0.0)  # holding
    assert opening(commander, jaw, a.t_grasp + 1.61) == pytest.approx(wide)  # let go
    assert commander.busy(a.t_grasp + 1.0) and not commander.busy(path.end_s + 0.01)


def test_an_update_replaces_the_rest_keeps_the_standby_and_does_not_reopen_the_jaw(arm) -> None:
    commander = Commander(arm)
    a = attempt(arm)
    commander.grasp(a)
    update = attempt(arm, T0 + 1.6, "u")  # begins after the jaw narrowed
    update.times, update.q, update.qd = update.times[:6], update.q[:6], update.qd[:6]
    update.t_grasp, update.final_from, update.t_close = T0 + 2.1, T0 + 1.7, T0 + 1.9
    update.standby = arm.q_home - 0.1  # solved anew since: the approved plan's still holds
    path, jaw = commander.grasp(update, update=True)
    np.testing.assert_allclose(path.q[-1], a.standby, atol=1e-9)
    spliced = commander.arm_path
    np.testing.assert_allclose(spliced.at(T0 + 1.0)[0], a.path(path.names).at(T0 + 1.0)[0])
    np.testing.assert_allclose(spliced.at(T0 + 1.65)[0], update.path(path.names).at(T0 + 1.65)[0])
    assert opening(commander, commander.jaw_path, T0 + 1.65) == pytest.approx(0.08)
    assert opening(commander, commander.jaw_path, T0 + 1.95) == pytest.approx(0.0)


def test_an_abort_backs_out_along_the_approach_from_the_commanded_state(arm) -> None:
    commander = Commander(arm, CommandConfig(retreat_m=0.08))
    a = attempt(arm)
    commander.grasp(a)
    now = T0 + 1.0
    q_now = commander.arm_path.at(now)[0]
    path, jaw = commander.abort(now)
    assert path.times[0] == pytest.approx(now)
    np.testing.assert_allclose(path.q[0], q_now, atol=1e-9)
    T = arm.forward(q_now)
    tool = np.array([arm.forward(q)[:3, 3] for q in path.q])
    back = (tool - T[:3, 3]) @ -T[:3, 2]  # along the approach, backwards
    assert back.max() == pytest.approx(0.08, abs=0.005)
    np.testing.assert_allclose(path.q[-1], a.standby, atol=1e-9)
    assert opening(commander, jaw, now + 1e-4) == pytest.approx(arm.jaw_max_opening_m)
    assert commander.arm_path.at(now + 0.5)[0] == pytest.approx(path.at(now + 0.5)[0])


def test_a_standby_move_waits_for_the_arm_to_be_idle(arm) -> None:
    commander = Commander(arm)
    names = list(arm.joint_names)
    move = JointPath(names, [T0, T0 + 1.0], [arm.q_home, arm.q_home + 0.1],
                     np.zeros((2, len(names))))
    assert commander.standby(move, T0) is move  # idle: taken
    assert commander.standby(move, T0 + 0.5) is None  # that move is under way
    with pytest.raises(ValueError, match="standby joint_names"):
        commander.standby(JointPath(["x"], [T0], [[0.0]], [[0.0]]), T0 + 5)


def test_paths_check_their_shapes_and_times(arm) -> None:
    with pytest.raises(ValueError, match="increase strictly"):
        JointPath(["a"], [1.0, 1.0], [[0.0], [1.0]], [[0.0], [0.0]])
    with pytest.raises(ValueError, match="must have shape"):
        JointPath(["a", "b"], [1.0], [[0.0]], [[0.0]])
    with pytest.raises(ValueError, match="finite"):
        JointPath(["a"], [1.0], [[np.nan]], [[0.0]])
    with pytest.raises(ValueError, match="joint names"):
        JointPath(["a"], [1.0], [[0.0]], [[0.0]]).then(JointPath(["b"], [2.0], [[0.0]], [[0.0]]))


def test_a_path_travels_as_a_joint_trajectory(arm) -> None:
    path, _jaw = Commander(arm).grasp(attempt(arm))
    names, times, q, qd = decode_joint_trajectory(encode_joint_trajectory(
        path.names, path.times, path.q, path.qd))
    assert names == path.names
    np.testing.assert_allclose(times, path.times, atol=1e-9)
    np.testing.assert_allclose(q, path.q)
    np.testing.assert_allclose(qd, path.qd)
    with pytest.raises(ValueError, match="not a valid trajectory_msgs/msg/JointTrajectory"):
        decode_joint_trajectory(b"\x00\x01\x00\x00\x05")
    with pytest.raises(ValueError, match="no points"):
        decode_joint_trajectory(encode_joint_trajectory([], np.zeros(0), np.zeros((0, 0)),
                                                        np.zeros((0, 0))))

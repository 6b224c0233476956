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
    path, jaw = commander.grasp(update, update=True, now_s=T0 + 0.9)  # approved then
    np.testing.assert_allclose(path.q[-1], a.standby, atol=1e-9)
    assert commander.arm_path.times[0] <= T0 + 0.9 < commander.arm_path.times[1]  # no more
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


def rosbags_trajectory(stamp_ns: int, frame_id: str, names: list[str], from_start_ns: list[int],
                       arrays: list[list[np.ndarray]]) -> bytes:
    """The same message serialised by rosbags: arrays per point are positions, velocities,
    accelerations, effort."""
    from wavegrasp.recording_io.typestore import ros2_typestore

    store = ros2_typestore()
    t = store.types
    points = [t["trajectory_msgs/msg/JointTrajectoryPoint"](
        positions=a[0], velocities=a[1], accelerations=a[2], effort=a[3],
        time_from_start=t["builtin_interfaces/msg/Duration"](sec=d // 10**9, nanosec=d % 10**9))
        for d, a in zip(from_start_ns, arrays, strict=True)]
    msg = t["trajectory_msgs/msg/JointTrajectory"](
        header=t["std_msgs/msg/Header"](stamp=t["builtin_interfaces/msg/Time"](
            sec=stamp_ns // 10**9, nanosec=stamp_ns % 10**9), frame_id=frame_id),
        joint_names=names, points=points)
    return bytes(store.serialize_cdr(msg, "trajectory_msgs/msg/JointTrajectory"))


def test_trajectories_are_written_and_read_byte_for_byte_as_rosbags_does() -> None:
    from wavegrasp.recording_io.joint_cdr import parse_joint_trajectory

    rng = np.random.default_rng(3)
    for case in range(40):
        n, k = int(rng.integers(1, 8)), int(rng.integers(1, 30))
        names = ["j" * int(rng.integers(1, 9)) + str(i) for i in range(n)]
        stamp = int(rng.integers(0, 2**31)) * 10**9 + int(rng.integers(0, 10**9))
        steps = rng.integers(1, 10**8, k)
        steps[0] = 0
        from_start = np.cumsum(steps).tolist()
        q, qd = rng.normal(size=(k, n)), rng.normal(size=(k, n))
        times = (stamp + np.array(from_start)) * 1e-9
        ours = encode_joint_trajectory(names, times, q, qd)
        stamp_s = int(round(times[0] * 1e9))  # as ours rounds it
        theirs = rosbags_trajectory(stamp_s, "", names, [int(round(t * 1e9)) - stamp_s
                                                         for t in times],
                                    [[q[i], qd[i], np.zeros(0), np.zeros(0)] for i in range(k)])
        assert ours == theirs, case
        # rosbags' bytes with every array filled, a frame and no velocities read alike
        full = [[q[i], np.zeros(0) if case % 2 else qd[i], q[i] * 2, q[i] * 3]
                for i in range(k)]
        msg = parse_joint_trajectory(rosbags_trajectory(stamp, "base" * (case % 3), names,
                                                        from_start, full))
        assert (msg.stamp_ns, msg.frame_id, msg.names) == (stamp, "base" * (case % 3), names)
        assert msg.from_start_ns == from_start
        np.testing.assert_array_equal(np.array(msg.positions), q)
        got = decode_joint_trajectory(rosbags_trajectory(stamp, "", names, from_start, full))
        np.testing.assert_array_equal(got[3], 0.0 if case % 2 else qd)
    for n in range(len(ours)):  # every truncation is refused, naming the type
        with pytest.raises(ValueError, match="not a valid trajectory_msgs/msg/JointTrajectory"):
            parse_joint_trajectory(ours[:n])


def test_joint_states_are_written_and_read_byte_for_byte_as_rosbags_does() -> None:
    from wavegrasp.recording_io.joint_cdr import parse_joint_state
    from wavegrasp.recording_io.ros_msgs import decode_joint_state, encode_joint_state
    from wavegrasp.recording_io.typestore import ros2_typestore

    store, rng = ros2_typestore(), np.random.default_rng(5)
    t = store.types
    for case in range(20):
        n = int(rng.integers(0, 9))
        names = ["f" * int(rng.integers(1, 6)) + str(i) for i in range(n)]
        stamp = int(rng.integers(0, 2**31)) * 10**9 + int(rng.integers(0, 10**9))
        p, v = rng.normal(size=n), rng.normal(size=n)
        effort = np.zeros(0) if case % 2 else rng.normal(size=n)
        theirs = bytes(store.serialize_cdr(t["sensor_msgs/msg/JointState"](
            header=t["std_msgs/msg/Header"](stamp=t["builtin_interfaces/msg/Time"](
                sec=stamp // 10**9, nanosec=stamp % 10**9), frame_id="" if case % 2 else "base"),
            name=names, position=p, velocity=v, effort=effort), "sensor_msgs/msg/JointState"))
        got = parse_joint_state(theirs)
        assert got[:2] == (stamp, names)
        for ours, want in zip(got[2:], (p, v, effort), strict=True):
            np.testing.assert_array_equal(ours, want)
        if case % 2:  # no efforts, no frame: what ours writes
            assert encode_joint_state(stamp, names, p, v) == theirs, case
            assert decode_joint_state(theirs)[0] == stamp
        for k in range(len(theirs)):
            with pytest.raises(ValueError, match="not a valid sensor_msgs/msg/JointState"):
                parse_joint_state(theirs[:k])

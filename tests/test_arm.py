"""The arm model: the packaged URDF loads in pybullet and agrees with our kinematics; IK."""

from __future__ import annotations

import re
from importlib.resources import files
from pathlib import Path

import numpy as np
import pybullet as pb
import pytest

from wavegrasp.arm import DEFAULT_URDF, ArmModel
from wavegrasp.arm.limits import DEFAULTS
from wavegrasp.arm.transforms import rotation_vector

URDF = Path(str(files("wavegrasp.arm") / DEFAULT_URDF))


@pytest.fixture(scope="module")
def arm() -> ArmModel:
    return ArmModel.load()


def random_q(arm: ArmModel, rng: np.random.Generator) -> np.ndarray:
    return rng.uniform(arm.lower, arm.upper)


def test_pybullet_forward_kinematics_matches(arm: ArmModel) -> None:
    client = pb.connect(pb.DIRECT)
    try:
        body = pb.loadURDF(str(URDF), useFixedBase=True, physicsClientId=client)
        info = [pb.getJointInfo(body, i, physicsClientId=client)
                for i in range(pb.getNumJoints(body, physicsClientId=client))]
        index = {i[1].decode(): i[0] for i in info}
        link_index = {i[12].decode(): i[0] for i in info}
        assert [info[index[n]][2] for n in arm.jaw_joints] == [pb.JOINT_PRISMATIC] * 2
        assert sum(info[index[n]][9] for n in arm.jaw_joints) == pytest.approx(0.14)
        assert arm.jaw_max_opening_m == pytest.approx(0.14)
        rng = np.random.default_rng(0)
        for _ in range(20):
            q = random_q(arm, rng)
            for name, value in zip(arm.joint_names, q, strict=True):
                pb.resetJointState(body, index[name], value, physicsClientId=client)
            state = pb.getLinkState(body, link_index["tool"], computeForwardKinematics=True,
                                    physicsClientId=client)
            T = arm.forward(q)
            np.testing.assert_allclose(arm.forward_batch(np.array([q, q]))[1], T, atol=1e-12)
            R = np.array(pb.getMatrixFromQuaternion(state[5])).reshape(3, 3)
            assert np.allclose(state[4], T[:3, 3], atol=1e-6)
            assert np.allclose(R, T[:3, :3], atol=1e-6)
    finally:
        pb.disconnect(client)


def test_jacobian_matches_finite_differences(arm: ArmModel) -> None:
    rng = np.random.default_rng(1)
    h = 1e-6
    for _ in range(10):
        q = random_q(arm, rng)
        T = arm.forward(q)
        J = arm.jacobian(q)
        assert J.shape == (6, 6)
        for i in range(6):
            dq = np.zeros(6)
            dq[i] = h
            T2 = arm.forward(q + dq)
            assert np.allclose((T2[:3, 3] - T[:3, 3]) / h, J[:3, i], atol=1e-5)
            assert np.allclose(rotation_vector(T2[:3, :3] @ T[:3, :3].T) / h, J[3:, i],
                               atol=1e-5)


def assert_solution(arm: ArmModel, q: np.ndarray, T: np.ndarray) -> None:
    assert arm.within_limits(q)
    T_q = arm.forward(q)
    assert np.linalg.norm(T_q[:3, 3] - T[:3, 3]) <= 1e-3
    assert np.degrees(np.linalg.norm(rotation_vector(T[:3, :3] @ T_q[:3, :3].T))) <= 2.0


@pytest.mark.parametrize("start", ["nearby", "home"])
def test_inverse_recovers_reachable_poses(arm: ArmModel, start: str) -> None:
    rng = np.random.default_rng(2)
    n, solved = 200, 0
    for _ in range(n):
        q_true = random_q(arm, rng)
        T = arm.forward(q_true)
        seed = arm.q_home if start == "home" else np.clip(
            q_true + rng.normal(0.0, 0.15, 6), arm.lower, arm.upper)
        q = arm.inverse(T, seed)
        if q is not None:
            assert_solution(arm, q, T)
            assert np.array_equal(q, arm.inverse(T, seed))  # deterministic
            solved += 1
    assert solved >= 0.95 * n


def test_inverse_gives_none_out_of_reach(arm: ArmModel) -> None:
    T = np.eye(4)
    T[:3, 3] = [2.0, 0.0, 0.2]
    assert arm.inverse(T, arm.q_home) is None
    assert arm.inverse_position(np.array([0.0, 2.0, 0.2]), np.array([0.0, 1.0, 0.0]),
                                arm.q_home) is None


def test_inverse_position_frees_rotation_about_the_approach(arm: ArmModel) -> None:
    rng = np.random.default_rng(3)
    for _ in range(30):
        p = np.array([rng.uniform(0.5, 0.8), rng.uniform(-0.3, 0.3), rng.uniform(-0.3, 0.3)])
        approach = np.array([1.0, rng.uniform(-0.5, 0.5), rng.uniform(-0.7, 0.2)])
        approach /= np.linalg.norm(approach)
        result = arm.inverse_position(p, approach, arm.q_home)
        assert result is not None
        q, T = result
        assert arm.within_limits(q)
        assert np.allclose(T, arm.forward(q))
        assert np.linalg.norm(T[:3, 3] - p) <= 1e-3
        assert np.degrees(np.arccos(np.clip(T[:3, 2] @ approach, -1, 1))) <= 2.0
        assert abs(q[-1] - arm.q_home[-1]) <= np.pi / 2 + 1e-6  # the jaw flip nearest home


def test_limits_and_checks(arm: ArmModel) -> None:
    assert arm.joint_names == ["base_yaw", "shoulder_pitch", "elbow_pitch", "forearm_roll",
                               "wrist_pitch", "wrist_roll"]
    assert arm.base_link == "bravo_base_link"
    assert arm.tool_link == "tool"
    assert arm.within_limits(arm.q_home)
    assert np.all((arm.max_velocity >= 1.0) & (arm.max_velocity <= 2.5))
    # Read from the file's <wavegrasp><limits> block, not the loader's defaults.
    np.testing.assert_array_equal(arm.max_acceleration, [6, 5, 6, 8, 10, 10])
    np.testing.assert_array_equal(arm.max_jerk, [80, 60, 80, 100, 120, 120])
    q = arm.q_home.copy()
    q[2] = 3.0
    assert not arm.within_limits(q)
    with pytest.raises(ValueError, match="elbow_pitch"):
        arm.check_q(q)
    with pytest.raises(ValueError, match="shape"):
        arm.check_q(np.zeros(5))


def test_overrides_apply() -> None:
    arm = ArmModel.load(overrides={"wrist_roll": {"max_velocity": 0.5, "upper": 1.0}})
    assert arm.joints["wrist_roll"].max_velocity == 0.5
    assert arm.max_velocity[5] == 0.5 and arm.upper[5] == 1.0
    with pytest.raises(ValueError, match="unknown joint"):
        ArmModel.load(overrides={"no_such_joint": {"max_velocity": 0.5}})
    with pytest.raises(ValueError, match="unknown fields"):
        ArmModel.load(overrides={"wrist_roll": {"speed": 0.5}})
    with pytest.raises(ValueError, match="max_jerk"):
        ArmModel.load(overrides={"wrist_roll": {"max_jerk": 0.0}})


def test_user_urdf_path(tmp_path: Path) -> None:
    text = URDF.read_text()
    text = text.replace('effort="80" velocity="1.2"', 'effort="80" velocity="0.7"')
    text = re.sub(r"\n  <wavegrasp>.*</wavegrasp>", "", text, flags=re.S)  # no extra limits
    path = tmp_path / "my_arm.urdf"
    path.write_text(text)
    arm = ArmModel.load(path)
    assert arm.joints["elbow_pitch"].max_velocity == 0.7
    assert arm.joints["elbow_pitch"].max_acceleration == DEFAULTS["revolute"]["max_acceleration"]
    assert arm.joints["finger_left"].max_jerk == DEFAULTS["prismatic"]["max_jerk"]
    assert arm.jaw_joints == ["finger_left", "finger_right"]  # found as prismatic side joints
    assert arm.jaw_max_opening_m == pytest.approx(0.14)
    assert np.all(arm.q_home == 0.0)
    with pytest.raises(ValueError, match="does not exist"):
        ArmModel.load(tmp_path / "missing.urdf")


def test_reach_and_capsules(arm: ArmModel) -> None:
    assert 0.9 <= arm.reach_m <= 1.1
    shoulder = arm.forward_all(np.zeros(6))[arm.link_names.index("upper_arm")][:3, 3]
    assert np.linalg.norm(arm.forward(np.zeros(6))[:3, 3] - shoulder) == pytest.approx(
        arm.reach_m)
    capsules = arm.link_capsules(arm.q_home)
    assert len(capsules) == 12  # six moving links; two flat fingers of three side by side
    assert all(p0.shape == (3,) and p1.shape == (3,) and r > 0 for p0, p1, r in capsules)
    closed = arm.link_capsules(arm.q_home, jaw_opening_m=0.0)
    gap = np.linalg.norm(closed[-1][0] - closed[-4][0])
    assert gap < np.linalg.norm(capsules[-1][0] - capsules[-4][0])
    # Wide open, the fingers' capsules leave nearly all of the jaw's 14 cm between them.
    left, right = capsules[-6:-3], capsules[-3:]
    inner = min(np.linalg.norm(a[0] - b[0]) - a[2] - b[2] for a, b in zip(left, right, strict=True))
    assert arm.jaw_max_opening_m - 0.006 <= inner <= arm.jaw_max_opening_m


def test_capsules_batch_matches_one_at_a_time(arm: ArmModel) -> None:
    rng = np.random.default_rng(4)
    qs = np.array([random_q(arm, rng) for _ in range(5)])
    p0, p1, radius = arm.capsules_batch(qs, jaw_opening_m=0.05)
    for k, q in enumerate(qs):
        one = arm.link_capsules(q, jaw_opening_m=0.05)
        np.testing.assert_allclose(p0[k], [c[0] for c in one], atol=1e-12)
        np.testing.assert_allclose(p1[k], [c[1] for c in one], atol=1e-12)
        np.testing.assert_allclose(radius, [c[2] for c in one])
    # The hand moves with the tool: its capsules sit still in the tool frame.
    hand0, hand1, _ = arm.hand_capsules
    T = arm.forward(qs[0])
    palm = [c for c in arm.link_capsules(qs[0])[:-arm.jaw_capsule_count]
            if np.allclose(c[0], T[:3, :3] @ hand0[0] + T[:3, 3], atol=1e-9)]
    assert len(palm) == 1
    np.testing.assert_allclose(palm[0][1], T[:3, :3] @ hand1[0] + T[:3, 3], atol=1e-9)


def test_facing_turns_the_first_joint_towards_a_target_anywhere(arm: ArmModel) -> None:
    for angle in np.radians([-150.0, -90.0, 0.0, 60.0, 120.0]):
        target = arm.shoulder + 0.6 * np.array([np.cos(angle), np.sin(angle), -0.2])
        q = arm.facing(target)
        tool = arm.forward(q)[:3, 3]
        assert np.arctan2(tool[1], tool[0]) == pytest.approx(angle, abs=1e-6)
        np.testing.assert_allclose(q[1:], arm.q_home[1:])
        # A grasp beside or behind the home pose's reach is found from its side.
        T = np.eye(4)
        T[:3, 3] = target
        T[:3, :3] = [[0, -np.sin(angle), np.cos(angle)], [0, np.cos(angle), np.sin(angle)],
                     [-1, 0, 0]]
        assert arm.inverse(T, arm.q_home, max_iter=40, restarts=0) is not None

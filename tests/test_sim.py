"""The PyBullet sim follows the commanded paths and judges each grasp physically (the paper's
Table II)."""

from __future__ import annotations

import contextlib
from collections.abc import Callable

import numpy as np
import pytest

from wavegrasp.arm import ArmModel
from wavegrasp.arm.motion import JointPath
from wavegrasp.gate.command import Commander
from wavegrasp.planner.approach import PredictedPath
from wavegrasp.planner.collision import Body
from wavegrasp.planner.plan import Plan, PlannerConfig, plan_grasp
from wavegrasp.schemas import Header
from wavegrasp.sim.executor import Attempt, Executor, Result
from wavegrasp.sim.world import ObjectShape, SimWorld
from wavegrasp.wavetank.record import arm_mount, pose_matrix
from wavegrasp.wavetank.scenario import paper_scenario

OMEGA = 2 * np.pi / 1.08
CAN = ObjectShape("cylinder", 0.033, 0.122)
BODY = Body(0.033, 0.061, np.array([0.0, 0.0, 1.0]))
UPRIGHT = np.array([0.0, 0.0, 0.0, 1.0])
NOW = 10.0


def swing(t: float) -> np.ndarray:
    """The can's true centroid (3,): a 6 cm swing along x, rising twice per swing."""
    return np.array([0.06 * np.sin(OMEGA * t), 0.003 * np.sin(OMEGA * t + 1.0),
                     0.525 - 0.004 * np.cos(2 * OMEGA * t)])


@pytest.fixture(scope="module")
def arm() -> ArmModel:
    return ArmModel.load()


@pytest.fixture(scope="module")
def T_world_base() -> np.ndarray:
    return pose_matrix(*arm_mount(paper_scenario(1, "buoy")))


def plan_for(arm: ArmModel, T_world_base: np.ndarray, offset=(0.0, 0.0, 0.0)
             ) -> tuple[Plan, PredictedPath]:
    """The planner's plan for a prediction that is the truth shifted by ``offset``, and that
    prediction."""
    t = NOW + np.arange(41) * 0.1
    path = PredictedPath(t, np.array([swing(x) for x in t]) + offset, np.full(41, 0.002),
                         2 * np.pi / OMEGA)
    plan = plan_grasp(path, NOW, arm, T_world_base, arm.q_home, BODY, PlannerConfig())
    assert isinstance(plan, Plan), plan
    return plan, path


def cylinder_vertices(radius: float, length: float, sides: int = 24) -> np.ndarray:
    """A closed cylinder's hull vertices (2 * sides, 3) around the origin, along z."""
    a = np.linspace(0.0, 2 * np.pi, sides, endpoint=False)
    ring = np.column_stack([radius * np.cos(a), radius * np.sin(a), np.zeros(sides)])
    return np.vstack([ring - (0, 0, length / 2), ring + (0, 0, length / 2)])


def execute(arm: ArmModel, T_world_base: np.ndarray, planned: tuple[Plan, PredictedPath],
            late_s: float = 0.0, truth: Callable[[float], np.ndarray] = swing,
            mesh: np.ndarray | None = None, shape: ObjectShape = CAN,
            close_s: float | None = None, jaw: list[tuple[float, float]] | None = None
            ) -> Result:
    """Run the plan (approved at NOW) against the ``truth``, the object (``shape``, the can) on
    its tether (and made ``mesh`` once placed, as the service does when perception's mesh
    arrives); the jaw starts closing at ``close_s`` (default the plan's), and its opening at
    every step is appended to ``jaw`` as (time s, metres)."""
    plan, path = planned
    attempt = Attempt("p", plan.times + late_s, plan.q, plan.qd, plan.t_grasp + late_s,
                      plan.grasp_T_world[:3, 3], plan.t_final + late_s, plan.jaw_preshape_m,
                      (plan.t_close if close_s is None else close_s) + late_s,
                      (path.times_s, path.positions), NOW)
    world = SimWorld(arm, T_world_base, shape)
    try:
        world.place_object(truth(NOW), UPRIGHT)
        assert world.add_tether()
        if mesh is not None:
            world.use_mesh(mesh)
        world.step_to(NOW)
        executor = Executor(world)
        for path in Commander(arm).grasp(attempt):  # as the gate commands it
            executor.follow(path)
        executor.start(attempt)
        for t in NOW + np.arange(1, 1000) * 0.01:  # ground truth at 100 Hz
            result = executor.advance(t, truth(t), UPRIGHT)
            if jaw is not None:
                jaw.append((t, world.jaw_opening()))
            if result is not None:
                assert not executor.attempt
                assert executor.returning and executor.busy  # heads back to its standby
                return result
        raise AssertionError("the attempt was never judged")
    finally:
        world.close()


def test_a_plan_that_ends_on_the_object_grasps_it(arm, T_world_base) -> None:
    result = execute(arm, T_world_base, plan_for(arm, T_world_base))
    assert result.success and result.failure is None, result
    assert result.evidence["fingers_touching"] == 2
    assert result.evidence["jaw_opening_m"] == pytest.approx(2 * CAN.radius_m, abs=0.004)


def test_a_jaw_that_starts_closing_before_its_final_move_is_not_reopened(arm, T_world_base
                                                                         ) -> None:
    planned = plan_for(arm, T_world_base)
    plan = planned[0]
    assert plan.jaw_preshape_m > 0  # the final move narrows the jaw: here it must not
    jaw: list[tuple[float, float]] = []
    close_s = plan.t_final - 0.04
    result = execute(arm, T_world_base, planned, close_s=close_s, jaw=jaw)
    times, opening = np.array(jaw).T
    closing = (times > close_s + 0.02) & (times < plan.t_grasp)
    assert np.all(np.diff(opening[closing]) <= 1e-4), "the jaw opened again while closing"
    assert opening[closing][-1] < opening[closing][0] - 0.02
    assert result.evidence["jaw_opening_m"] < 2 * CAN.radius_m + 0.005, result


def test_an_object_deep_in_the_jaw_is_held(arm, T_world_base) -> None:
    # A 4 cm bottle's body that comes 5 cm short of the grasp point along the approach (the
    # palm 2 cm behind it): the jaw closes on it there and holds it, 5 cm from the grasp
    # point, as the water pulls it towards the arm.
    thin = ObjectShape("cylinder", 0.02, 0.2)
    planned = plan_for(arm, T_world_base)
    back = -planned[0].grasp_T_world[:3, 2]
    result = execute(arm, T_world_base, planned, shape=thin,
                     truth=lambda t: swing(t) + 0.05 * back)
    assert result.success, result
    assert result.evidence["object_in_jaw_m"] < -0.03, result.evidence
    assert result.evidence["object_from_tool_m"] > 0.05, result.evidence


def test_the_mesh_replaces_the_fitted_shape_and_is_grasped(arm, T_world_base) -> None:
    import pybullet as pb

    # A hull 2 mm wider than the fitted cylinder: the jaw must close on the mesh.
    mesh = cylinder_vertices(CAN.radius_m + 0.002, CAN.length_m)
    result = execute(arm, T_world_base, plan_for(arm, T_world_base), mesh=mesh)
    assert result.success, result
    assert result.evidence["jaw_opening_m"] == pytest.approx(2 * CAN.radius_m + 0.004,
                                                             abs=0.004)
    world = SimWorld(arm, T_world_base, CAN)
    try:
        world.place_object(swing(NOW), UPRIGHT)
        world.use_mesh(mesh)
        assert pb.getCollisionShapeData(world.object, -1, physicsClientId=world.client)[0][2] \
            == pb.GEOM_MESH
        assert np.allclose(world.object_position(), swing(NOW))
        with pytest.raises(ValueError, match="mesh vertices"):
            world.use_mesh(mesh[:3])
    finally:
        world.close()


def test_an_arm_that_touches_the_tether_fails_as_collision(arm, T_world_base) -> None:
    planned = plan_for(arm, T_world_base)
    in_the_way = planned[0].tool[len(planned[0].tool) // 2]  # where the arm passes
    # The can waits 30 cm above that point: its tether is in the way first.
    above = in_the_way + (0.0, 0.0, 0.30 + CAN.length_m / 2)
    result = execute(arm, T_world_base, planned, truth=lambda t: above)
    assert not result.success and result.failure == "collision", result
    assert result.evidence["link"].endswith("on the tether"), result.evidence


def test_a_plan_5_cm_off_fails_as_prediction_error(arm, T_world_base) -> None:
    # 5 cm towards the arm, across the swing: the object never comes to the grasp point.
    result = execute(arm, T_world_base, plan_for(arm, T_world_base, (0.0, -0.05, 0.0)))
    assert not result.success and result.failure == "prediction", result
    assert result.evidence["object_from_p_f_at_grasp_m"] == pytest.approx(0.05, abs=0.005)


def test_a_plan_that_sweeps_through_the_object_fails_as_collision(arm, T_world_base) -> None:
    planned = plan_for(arm, T_world_base)
    in_the_way = planned[0].tool[len(planned[0].tool) // 2]  # it waits where the arm passes
    result = execute(arm, T_world_base, planned, truth=lambda t: in_the_way)
    assert not result.success and result.failure == "collision", result
    assert result.evidence["before_grasp_s"] > 0


def test_motion_that_changes_after_approval_fails_as_abrupt_change(arm, T_world_base) -> None:
    # The prediction held when the plan was approved; 1 s later the object is carried 5 cm
    # away from the arm (a gust, a snagged tether) and keeps swinging there.
    def truth(t: float) -> np.ndarray:
        return swing(t) + (0.0, 0.05 * min(max(t - NOW - 1.0, 0.0) / 0.3, 1.0), 0.0)

    result = execute(arm, T_world_base, plan_for(arm, T_world_base), truth=truth)
    assert not result.success and result.failure == "abrupt_change", result
    assert result.evidence["strayed_m"] > 0.04
    assert result.evidence["strayed_after_approval_s"] == pytest.approx(1.12, abs=0.1)


def test_a_plan_300_ms_late_fails_as_timing(arm, T_world_base) -> None:
    result = execute(arm, T_world_base, plan_for(arm, T_world_base), late_s=0.3)
    assert not result.success and result.failure == "timing", result
    assert result.evidence["arm"] == "late"
    assert result.evidence["object_passed_s"] == pytest.approx(-0.3, abs=0.03)


def test_attempt_from_a_plan_message_names_what_is_wrong(arm) -> None:
    from wavegrasp.schemas import GraspPlan, Pose, Quaternion, Vec3

    msg = GraspPlan(header={"seq": 1, "stamp_ns": 1}, plan_id="x", t_start_ns=1, t_grasp_ns=2,
                    grasp=Pose(position=Vec3(x=0, y=0, z=0),
                               orientation=Quaternion(x=0, y=0, z=0, w=1)),
                    approach=Vec3(x=0, y=0, z=-1))
    with pytest.raises(ValueError, match="no joint_trajectory"):
        Attempt.from_message(msg, arm.joint_names)


@contextlib.contextmanager
def trial_sim(arm, T_world_base, **settings):
    """A sim service on its own bus, its world built with the can, stopping after its
    trials."""
    from wavegrasp.runtime.bus import Bus
    from wavegrasp.runtime.settings import Settings
    from wavegrasp.sim.main import SimService, SimSettings

    bus = Bus(Settings(service="sim", zenoh_mode="peer", zenoh_connect=[], zenoh_listen=[]))
    sim = SimService(SimSettings(service="sim", stop_after_trials=True, **settings), bus=bus)
    try:
        sim.world = SimWorld(arm, T_world_base, CAN)
        sim.executor = Executor(sim.world)
        yield sim
    finally:
        if sim.world is not None:
            sim.world.close()
        bus.close()


def test_trials_end_at_a_success_after_the_last_attempt_or_waiting(arm, T_world_base) -> None:
    with trial_sim(arm, T_world_base, trials=3, attempts=2, trial_timeout_s=10.0) as sim:
        sim.world.time_s = 100.0
        sim.attempt = 1
        sim.publish_outcome(Result("a", False, "timing"))  # trial 0, attempt 1 of 2
        assert (sim.trial, sim.attempt) == (0, 1)
        sim.attempt = 2
        sim.publish_outcome(Result("b", False, "prediction"))  # its last attempt
        assert (sim.trial, sim.attempt) == (1, 0)
        sim.attempt = 1
        sim.publish_outcome(Result("c", True, None))  # a success ends trial 1
        assert (sim.trial, sim.attempt) == (2, 0) and not sim.stopping.is_set()
        sim.world.time_s = 109.0
        sim.check_trial_timeout()  # 9 s without an approved plan: still waiting
        assert sim.trial == 2
        sim.world.time_s = 110.5
        sim.check_trial_timeout()  # 10 s: trial 2 ends as a failure, and with it the run
        assert sim.trial == 3 and sim.stopping.is_set()
        assert sim.counters["trials ended waiting for a plan"] == 1


def test_a_warm_prediction_begins_the_trials_though_no_plan_ever_comes(arm, T_world_base
                                                                        ) -> None:
    """A predictor too unsure to be planned on gives the gate nothing to decide: its trials
    still begin at the first warm prediction and end, failed, after the timeout."""
    from wavegrasp.schemas import Header, MotionPrediction, PredictionSample

    def prediction(warm: bool) -> MotionPrediction:
        return MotionPrediction(
            header=Header(seq=1, stamp_ns=10**9), model="linear",
            period_s=1.5, warm=warm, samples=[PredictionSample(
                t_ns=10**9 + k * 10**8, x=0.0, y=0.0, z=0.5, sigma=0.2) for k in range(3)])

    with trial_sim(arm, T_world_base, trials=2, attempts=3, trial_timeout_s=5.0) as sim:
        sim.on_prediction(prediction(warm=False), None)
        sim.finish_frame(1)
        sim.world.time_s += 20.0
        sim.finish_frame(2)  # still warming up: no trial has begun, none can time out
        assert sim.trial == 0 and not sim.counters["trials ended waiting for a plan"]
        sim.on_prediction(prediction(warm=True), None)
        sim.finish_frame(3)  # trial 0 begins
        for k in range(2):
            sim.world.time_s += 5.0
            sim.finish_frame(4 + k)
        assert sim.counters["trials ended waiting for a plan"] == 2
        assert sim.trial == 2 and sim.stopping.is_set()


def test_the_service_reshapes_the_object_only_between_attempts(arm, T_world_base) -> None:
    import pybullet as pb

    from wavegrasp.runtime.bus import Bus
    from wavegrasp.runtime.settings import Settings
    from wavegrasp.schemas import ObjectMesh
    from wavegrasp.schemas.mesh_codec import encode_mesh
    from wavegrasp.sim.main import SimService, SimSettings

    bus = Bus(Settings(service="sim", zenoh_mode="peer", zenoh_connect=[], zenoh_listen=[]))
    sim = SimService(SimSettings(service="sim"), bus=bus)
    hull = cylinder_vertices(CAN.radius_m, CAN.length_m)
    triangles = np.array([[0, 1, 2], [0, 2, 3]])  # the sim takes the hull of the vertices
    msg = ObjectMesh(header={"seq": 1, "stamp_ns": 1}, shape="cylinder", volume_m3=3e-4,
                     frames=10, **encode_mesh(hull, triangles))
    try:
        sim.world = SimWorld(arm, T_world_base, CAN)
        sim.executor = Executor(sim.world)
        sim.world.place_object(swing(NOW), UPRIGHT)
        sim.world.time_s = NOW
        shape = lambda: pb.getCollisionShapeData(sim.world.object, -1,  # noqa: E731
                                                 physicsClientId=sim.world.client)[0][2]
        sim.executor.start(Attempt("busy", np.array([NOW, NOW + 1]), np.zeros((2, 7)),
                                   np.zeros((2, 7)), NOW + 1, swing(NOW + 1), NOW, 0.0, NOW))
        sim.on_mesh(msg, None)
        sim.finish_frame(1)
        assert shape() == pb.GEOM_CYLINDER  # not under the gripper
        sim.executor.attempt = None
        sim.finish_frame(2)
        assert shape() == pb.GEOM_MESH and sim.counters["meshes used"] == 1
        with pytest.raises(ValueError, match="vertices_b64"):
            sim.on_mesh(msg.model_copy(update={"vertex_count": 47}), None)
    finally:
        sim.world.close()
        bus.close()


def test_a_restarted_sim_goes_on_with_its_trials(arm, T_world_base, tmp_path) -> None:
    """State noted at each frame survives a crash (no on_stop); the attempt under way when it
    died is reported failed; a clean stop forgets the state."""
    from wavegrasp.runtime.bus import Bus
    from wavegrasp.runtime.settings import Settings
    from wavegrasp.sim.main import SimService, SimSettings

    state = tmp_path / "sim.json"
    settings = SimSettings(service="sim", trials=5, attempts=3, resume_file=state)
    bus = Bus(Settings(service="sim", zenoh_mode="peer", zenoh_connect=[], zenoh_listen=[]))
    try:
        first = SimService(settings, bus=bus)
        first.world = SimWorld(arm, T_world_base, CAN)
        first.executor = Executor(first.world)
        first.trial, first.attempt, first._executing = 2, 1, "p7"
        first.finish_frame(1)  # notes the state; then the process is killed: no on_stop
        first.world.close()
        second = SimService(settings, bus=bus)
        assert (second.trial, second.attempt) == (2, 1)
        assert second.counters["attempts cut short by a restart"] == 1
        (cut,) = second._results
        assert cut.plan_id == "p7" and not cut.success and cut.failure == "other"
        second.on_stop()
        assert not state.exists()
        state.write_text("{not json")
        third = SimService(settings, bus=bus)  # an unreadable state: start afresh
        assert (third.trial, third.attempt) == (0, 0)
    finally:
        bus.close()


def test_a_pose_far_ahead_of_the_clock_is_refused_and_the_scene_goes_on(
        arm, T_world_base) -> None:
    """Taken, it would move the scene there, and every later pose would look older."""
    from wavegrasp.runtime.bus import Bus, Delivery
    from wavegrasp.runtime.settings import Settings
    from wavegrasp.schemas import Clock, Header
    from wavegrasp.sim.main import SimService, SimSettings

    from fuzz_cases import pose_cdr

    bus = Bus(Settings(service="sim", zenoh_mode="peer", zenoh_connect=[], zenoh_listen=[]))
    sim = SimService(SimSettings(service="sim"), bus=bus)
    now_ns = int(NOW * 1e9)

    def truth(t_ns: int) -> Delivery:
        return Delivery("groundtruth/object", pose_cdr(t_ns, tuple(swing(t_ns * 1e-9))),
                        "application/cdr", None, 0, 0)

    try:
        sim.world = SimWorld(arm, T_world_base, CAN)
        sim.executor = Executor(sim.world)
        sim.world.place_object(swing(NOW), UPRIGHT)
        sim.world.time_s = NOW
        sim.on_clock(Clock(header=Header(seq=1, stamp_ns=now_ns), rate=0.0), None)
        with pytest.raises(ValueError, match="ahead of the recording clock"):
            sim.on_truth(truth(now_ns + 3600 * 10**9))
        sim.on_truth(truth(now_ns + 10**8))  # 0.1 s on: taken
        assert sim.world.time_s == pytest.approx(NOW + 0.1, abs=1e-6)
    finally:
        sim.world.close()
        bus.close()


def test_an_approval_that_overtakes_its_plan_waits_for_it(arm, T_world_base) -> None:
    """The plan (from the planner) and its approval (from the gate) reach the sim through the
    router from two publishers, in either order: the frame the approval came in finishes, and
    the attempt starts, only once the plan is here, as in every lockstep run."""
    import time

    from wavegrasp.runtime.bus import Bus, Delivery
    from wavegrasp.runtime.settings import Settings
    from wavegrasp.schemas import FrameAck, GateDecision
    from wavegrasp.sim.main import SimService, SimSettings

    from fuzz_cases import example_plan, header

    bus = Bus(Settings(service="sim", zenoh_mode="peer", zenoh_connect=[], zenoh_listen=[]))
    sim = SimService(SimSettings(service="sim"), bus=bus)
    t0 = int(NOW * 1e9)
    plan = example_plan("late", t0)
    plan.joint_names = list(arm.joint_names)
    plan.joint_trajectory = [s.model_copy(update={"positions": list(arm.q_home)})
                             for s in plan.joint_trajectory]
    go = GateDecision(header=header(t0), plan_id="late", go=True, mean_error_m=0.001,
                      threshold_m=0.01, window_s=2.0)
    ack = FrameAck(header=header(t0, seq=7), service="gate", frame_seq=7)
    delivery = Delivery("wavegrasp/gate/ack", b"", "application/json", None, time.time_ns(), 0)
    try:
        sim.world = SimWorld(arm, T_world_base, CAN)
        sim.executor = Executor(sim.world)
        sim.world.place_object(swing(NOW), UPRIGHT)
        sim.world.time_s = NOW
        sim.on_decision(go, None)  # before its plan
        sim.on_upstream_ack(ack, delivery)  # the frame's end
        assert sim.counters["frames waiting for a plan"] == 1
        assert sim.attempt == 0 and not bus.bad
        sim.on_plan(plan, None)
        assert sim.attempt == 1 and sim._executing == "late"
        # An approval whose plan never comes is dropped, named, when the next one comes.
        sim.on_decision(go.model_copy(update={"plan_id": "lost"}), None)
        sim.on_decision(go.model_copy(update={"plan_id": "other"}), None)
        assert bus.last_bad_reason["wavegrasp/gate/decision"] == (
            "decision for plan lost that never arrived")
    finally:
        sim.world.close()
        bus.close()


def test_the_world_is_the_recordings_own_object_not_perceptions_view(arm) -> None:
    """A generated recording says what its object is: the sim builds that (a box here), and
    neither perception's fitted shape nor its mesh reshape it."""
    from wavegrasp.runtime.bus import Bus
    from wavegrasp.runtime.settings import Settings
    from wavegrasp.schemas import ObjectMesh, ObjectObservation, PlayerStatus
    from wavegrasp.schemas.mesh_codec import encode_mesh
    from wavegrasp.sim.main import SimService, SimSettings
    from wavegrasp.wavetank.scenario import ObjectModel, paper_scenario

    box = ObjectModel(family="box", diameter_m=0.08, depth_m=0.05, length_m=0.15, mass_kg=0.2)
    meta = {"scenario": paper_scenario(2, "buoy", object=box).model_dump_json()}
    bus = Bus(Settings(service="sim", zenoh_mode="peer", zenoh_connect=[], zenoh_listen=[]))
    sim = SimService(SimSettings(service="sim"), bus=bus)
    try:
        status = PlayerStatus(header={"seq": 0, "stamp_ns": 0}, state="playing",
                              recording="r.mcap", pace="lockstep", metadata=meta)
        sim.on_player_status(status, None)
        assert sim.shape is not None and sim.shape.shape == "box"
        v = sim.shape.vertices
        assert v is not None and np.ptp(v, axis=0) == pytest.approx([0.08, 0.05, 0.15])
        assert sim.shape.tether_offset_m == pytest.approx(0.075)
        sim.on_observation(ObjectObservation(
            header={"seq": 1, "stamp_ns": 1}, centroid={"x": 0, "y": 0, "z": 0.5},
            points_used=100, quality=1.0, sigma_m=0.001, shape="cylinder", radius_m=0.05,
            length_m=0.1), None)
        sim.on_mesh(ObjectMesh(header={"seq": 1, "stamp_ns": 1}, shape="cylinder",
                               volume_m3=3e-4, frames=10, **encode_mesh(
                                   cylinder_vertices(0.05, 0.1), np.array([[0, 1, 2]]))), None)
        assert sim.shape.shape == "box" and sim._mesh is None
        with pytest.raises(ValueError, match="metadata.scenario.object"):
            sim._truth_shape = False
            sim.on_player_status(status.model_copy(update={"metadata": {
                "scenario": '{"object": {"family": "cube"}}'}}), None)
    finally:
        bus.close()


def give_scene(sim, arm: ArmModel, T_world_base: np.ndarray) -> None:
    """The sim's world as the recording would build it: the can on its swing and its tether,
    at NOW; then the sim's subscriptions are known to the router."""
    import time

    sim.world = SimWorld(arm, T_world_base, CAN)
    sim.world.place_object(swing(NOW), UPRIGHT)
    assert sim.world.add_tether()
    sim.world.step_to(NOW)
    sim.executor = Executor(sim.world)
    time.sleep(0.5)


def test_the_arm_is_driven_only_by_joint_trajectories_and_reports_joint_states(
        router, arm, T_world_base) -> None:
    """The arm's whole interface is a ros2_control arm's: the commander's paths go in over
    the bus as ``trajectory_msgs/msg/JointTrajectory`` (arm and jaw), the sim follows them
    and sends ``sensor_msgs/msg/JointState`` once a camera frame; from those alone the grasp
    shows: both fingers stopped on the can, the tool at it while held, then the jaw open and
    the arm back at its standby. (The world, the can on its swing, is fed as the recording
    would; no plan, approval or any other message of ours reaches the sim.)"""

    from wavegrasp.recording_io.ros_msgs import (
        JOINT_TRAJECTORY,
        decode_joint_state,
        encode_joint_trajectory,
    )
    from wavegrasp.sim.main import SimService, SimSettings

    from conftest import wait_until

    plan, _path = plan_for(arm, T_world_base)
    attempt = Attempt("p", plan.times, plan.q, plan.qd, plan.t_grasp, plan.grasp_T_world[:3, 3],
                      plan.t_final, plan.jaw_preshape_m, plan.t_close, standby=arm.q_home)
    sim = SimService(SimSettings.from_env("sim", env=router.env))
    commander = router.bus("commander")
    states: list[tuple[int, list[str], np.ndarray, np.ndarray]] = []
    commander.subscribe(sim.cfg.joint_states_key,
                        lambda d: states.append(decode_joint_state(d.payload)))
    try:
        give_scene(sim, arm, T_world_base)
        arm_path, jaw_path = Commander(arm).grasp(attempt)
        for key, path in ((sim.cfg.arm_trajectory_key, arm_path),
                          (sim.cfg.jaw_trajectory_key, jaw_path)):
            commander.publish_cdr(key, encode_joint_trajectory(path.names, path.times, path.q,
                                                               path.qd), JOINT_TRAJECTORY)
        assert wait_until(lambda: sim.drain() >= 0 and len(sim._paths) == 2)
        frames = 0
        for k, t in enumerate(NOW + np.arange(1, 901) * 0.01):  # ground truth at 100 Hz
            sim.advance(t, swing(t), UPRIGHT)
            if k % 10 == 9:  # a camera frame every 0.1 s
                sim.finish_frame(frames)
                frames += 1
        def received() -> int:
            while not commander.inbox.empty():
                commander.dispatch(commander.inbox.get_nowait())
            return len(states)

        assert wait_until(lambda: received() == frames)
    finally:
        sim.world.close()
        sim.bus.close()
        commander.close()
    names = states[0][1]
    assert names == [*arm.joint_names, *arm.jaw_joints]
    n = len(arm.joint_names)
    stamps = np.array([s[0] for s in states]) * 1e-9
    q = np.array([s[2][:n] for s in states])
    fingers = np.array([s[2][n:] for s in states])
    held = np.flatnonzero((stamps > plan.t_grasp + 0.6) & (stamps < plan.t_grasp + 1.5))
    assert len(held) >= 8
    at_grasp = int(np.argmin(np.abs(stamps - plan.t_grasp)))  # the tool met the can
    tool = (T_world_base @ arm.forward(q[at_grasp]))[:3, 3]
    assert np.linalg.norm(tool - swing(stamps[at_grasp])) < 0.02
    for i in held:  # both fingers stopped on the can, held while the water pulls it
        assert fingers[i].sum() == pytest.approx(2 * CAN.radius_m, abs=0.004)
        assert fingers[i].min() > 0.01
    assert stamps[-1] > arm_path.end_s  # then let go and back to standby
    np.testing.assert_allclose(q[-1], arm.q_home, atol=0.01)
    assert fingers[-1].sum() == pytest.approx(arm.jaw_max_opening_m, abs=0.005)
    assert sim.counters["paths followed"] == 2


def test_the_arm_stops_and_holds_without_the_gates_heartbeat_and_takes_no_stale_path(
        router, arm, T_world_base) -> None:
    """The arm's watchdog (the link to the topside drops): while the gate's heartbeats come
    the arm follows its trajectory; once they stop for ``watchdog_s`` it holds where it is,
    its attempt ends aborted, and it refuses new paths; after the next heartbeat it takes
    fresh ones again, never one that started longer ago than ``freshness_s``."""
    import time

    from wavegrasp.recording_io.ros_msgs import JOINT_TRAJECTORY, encode_joint_trajectory
    from wavegrasp.schemas import HEARTBEAT_KEY, Heartbeat
    from wavegrasp.sim.main import SimService, SimSettings

    from conftest import wait_until

    plan, _path = plan_for(arm, T_world_base)
    attempt = Attempt("p", plan.times, plan.q, plan.qd, plan.t_grasp, plan.grasp_T_world[:3, 3],
                      plan.t_final, plan.jaw_preshape_m, plan.t_close, standby=arm.q_home)
    sim = SimService(SimSettings.from_env("sim", env=router.env, watchdog_s=0.3))
    gate = router.bus("gate")
    beats = 0

    def beat() -> None:
        nonlocal beats
        gate.publish(HEARTBEAT_KEY, Heartbeat(header=Header(seq=beats), period_s=0.1))
        beats += 1

    def send(path) -> None:
        key = sim.cfg.arm_trajectory_key if path.names == list(arm.joint_names) else \
            sim.cfg.jaw_trajectory_key
        gate.publish_cdr(key, encode_joint_trajectory(path.names, path.times, path.q, path.qd),
                         JOINT_TRAJECTORY)

    def advance(until: float) -> None:
        t = sim.world.time_s
        while t < until - 1e-9:
            t += 0.01
            sim.advance(t, swing(t), UPRIGHT)

    try:
        give_scene(sim, arm, T_world_base)
        beat()
        assert wait_until(lambda: sim.drain() >= 0 and sim.watchdog.last is not None)
        arm_path, jaw_path = Commander(arm).grasp(attempt)
        send(arm_path)
        send(jaw_path)
        assert wait_until(lambda: sim.drain() >= 0 and len(sim._paths) == 2)
        sim.follow_paths()
        sim.executor.start(attempt)
        advance(plan.times[0] + 0.5)  # under way
        moving_q = sim.world.arm_q()[0]
        sim.on_tick()
        assert sim.counters["watchdog: stopped, no heartbeat"] == 0  # the beat is recent
        time.sleep(0.4)  # no heartbeat for longer than watchdog_s
        sim.on_tick()
        assert sim.counters["watchdog: stopped, no heartbeat"] == 1
        assert 300 <= sim.counters["watchdog: the last stop, ms after the last heartbeat"] < 1000
        # The attempt under way ends there, aborted: its plan assumed an arm that went on.
        assert sim.counters["aborted"] == 1 and sim.executor.attempt is None
        stopped_at, held = sim.world.time_s, sim.executor.arm_path.at(sim.world.time_s)[0]
        advance(stopped_at + 1.0)  # the arm holds where it was commanded to be
        np.testing.assert_allclose(sim.world.arm_q()[0], held, atol=2e-3)
        assert np.linalg.norm(held - moving_q) > 0.01  # it had moved on its path meanwhile
        assert sim.executor.arm_path.end_s == stopped_at
        later = Commander(arm).grasp(attempt, now_s=sim.world.time_s)[0]
        send(later)  # the link is down: nothing new is taken
        assert wait_until(lambda: sim.drain() >= 0
                          and sim.counters["paths refused: no heartbeat"] == 1)
        beat()  # the link is back
        assert wait_until(lambda: sim.drain() >= 0 and not sim.watchdog.tripped)
        send(later)  # approved before the drop, delivered now: too old to carry out
        assert wait_until(lambda: sim.drain() >= 0 and sim.counters["paths refused: stale"] == 1)
        now = sim.world.time_s
        fresh = JointPath(list(arm.joint_names), [now + 0.1, now + 2.0], [held, arm.q_home],
                          np.zeros((2, len(held))))
        send(fresh)
        assert wait_until(lambda: sim.drain() >= 0 and len(sim._paths) == 1)
        sim.follow_paths()
        advance(now + 2.5)
        np.testing.assert_allclose(sim.world.arm_q()[0], arm.q_home, atol=0.01)
        assert sim.counters["paths followed"] == 3
    finally:
        sim.world.close()
        sim.bus.close()
        gate.close()

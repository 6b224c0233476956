"""How the fuzz test (``test_fuzz.py``) feeds the services at the pipeline's ends: sim, recorder
and player."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from mcap.reader import make_reader

from wavegrasp.arm import ArmModel
from wavegrasp.player.main import Player, PlayerSettings
from wavegrasp.recorder.main import Recorder, RecorderSettings
from wavegrasp.recording_io.own_messages import decode_own
from wavegrasp.recording_io.reader import open_recording
from wavegrasp.recording_io.ros_msgs import encode_clock
from wavegrasp.runtime.bus import CDR, JSON
from wavegrasp.runtime.service import Service
from wavegrasp.schemas import (
    ROS_KEYS,
    ArmState,
    FrameAck,
    GateAbort,
    GateDecision,
    ObjectMesh,
    ObjectObservation,
    PlayerStatus,
    Vec3,
    model_for_key,
)
from wavegrasp.schemas.mesh_codec import encode_mesh
from wavegrasp.sim.main import SimService, SimSettings

from conftest import wait_until
from fuzz_cases import (
    CDR_HEADER,
    EXAMPLES,
    JOINT_STATE_ENC,
    TRAJECTORY_ENC,
    Case,
    attachment,
    cloud_semantic_cases,
    example_plan,
    header,
    joint_state_cdr,
    joint_state_semantic_cases,
    message_case,
    pose_semantic_cases,
    store,
    tetrahedron,
    trajectory_cdr,
    trajectory_semantic_cases,
)
from fuzz_harness import SAMPLE, Harness, Scenario


class SimScenario(Scenario):
    name = "sim"

    def make(self) -> Service:
        self.i = 100  # the latest truth sample sent
        self.t_ns = int(self.sample.truth_ns[self.i])
        return SimService(SimSettings.from_env("sim", env=self.env))

    def truth_case(self, i: int | None = None, kind: str = "valid") -> Case:
        """Ground truth sample ``i`` (10 samples on by default), as the player sends it."""
        if i is None:
            self.i += 10
            self.t_ns = int(self.sample.truth_ns[self.i])
            i = self.i
        return Case(kind, self.sample.truth_cdr[i], f"{CDR};geometry_msgs/msg/PoseStamped",
                    None, attachment(i, int(self.sample.truth_ns[i])))

    def frame(self, h: Harness) -> ArmState:
        """A ground truth then the frame's end: the scene moves there and the arm is reported."""
        h.deliver("groundtruth/object", [self.truth_case()])
        self.acks += 1
        h.send_msg("wavegrasp/gate/ack", FrameAck(header=header(self.t_ns), service="gate",
                                                  frame_seq=self.acks))
        return h.wait_for("wavegrasp/sim/arm_state",
                          lambda s: s.header.seq == self.acks)

    def before(self, h: Harness) -> None:
        h.collect("wavegrasp/sim/arm_state", ArmState)
        h.deliver("tf_static", [self.valid("tf_static")])
        p = self.sample.truth_xyz[self.i]
        h.send_msg("wavegrasp/perception/object", ObjectObservation(
            header=header(self.t_ns), centroid=Vec3(x=p[0], y=p[1], z=p[2]), shape="sphere",
            radius_m=0.06, length_m=0.12))
        self.frame(h)
        assert h.service.world is not None

    def valid(self, key: str) -> Case:
        t = self.t_ns
        if key == "tf_static":
            return Case("valid", self.sample.tf, f"{CDR};tf2_msgs/msg/TFMessage", None)
        if key == "groundtruth/object":
            return self.truth_case()
        if key == "wavegrasp/perception/object":
            return message_case("valid", ObjectObservation(header=header(t), reason="no object"))
        if key == "wavegrasp/perception/mesh":
            return message_case("valid", ObjectMesh(header=header(t), shape="sphere",
                                                    volume_m3=1e-3, frames=20,
                                                    **tetrahedron(0.06)))
        if key == "wavegrasp/predictor/prediction":
            return message_case("valid", self.sample.prediction(self.i, seq=self.i))
        if key == "wavegrasp/planner/plan":
            return message_case("valid", example_plan("stored", t))
        if key in ("arm/joint_trajectory_controller/joint_trajectory",
                   "jaw/joint_trajectory_controller/joint_trajectory"):
            return self.trajectory(key)
        if key == "wavegrasp/player/status":  # the scene is built: its object stays
            return message_case("valid", EXAMPLES[PlayerStatus]().model_copy(
                update={"header": header(t), "metadata": {"scenario": '{"object": 1}'}}))
        if key == "wavegrasp/gate/decision":
            return message_case("valid", GateDecision(header=header(t), plan_id="stored",
                                                      go=False, mean_error_m=None,
                                                      threshold_m=0.01, window_s=2.0))
        if key == "wavegrasp/gate/abort":  # of a plan not executing: nothing to stop
            return message_case("valid", GateAbort(header=header(t), plan_id="stored",
                                                   reason="stale prediction"))
        return super().valid(key)

    def trajectory(self, key: str, kind: str = "valid", names: list[str] | None = None
                   ) -> Case:
        """A path holding the arm (or the jaw) where it is: its home pose (the jaw open)."""
        arm = ArmModel.load(None)
        if names is None:
            names = list(arm.jaw_joints if key.startswith("jaw/") else arm.joint_names)
        q = [0.02] * len(names) if key.startswith("jaw/") else list(arm.q_home)
        return Case(kind, trajectory_cdr(self.t_ns, names, [(0.1, q), (0.2, q)]),
                    TRAJECTORY_ENC, None)

    def cdr_basis(self, key: str) -> bytes:
        if key == "groundtruth/object":
            return self.sample.truth_cdr[0]
        return super().cdr_basis(key)

    def semantic(self, key: str) -> list[Case]:
        if key == "groundtruth/object":
            return pose_semantic_cases(self.t_ns + 1)
        if key.endswith("/joint_trajectory"):
            arm = ArmModel.load(None)
            return trajectory_semantic_cases(self.t_ns, list(arm.joint_names),
                                             list(arm.q_home))
        return super().semantic(key)

    def odd(self, key: str) -> list[Case]:
        t = self.t_ns
        if key == "groundtruth/object":  # the scene does not go back (checked after)
            return [self.truth_case(self.i, "duplicate pose"),
                    self.truth_case(self.i - 30, "older pose")]
        if key == "wavegrasp/gate/decision":
            go = GateDecision(header=header(t), plan_id="never-planned", go=True,
                              mean_error_m=0.001, threshold_m=0.01, window_s=2.0)
            return [message_case("go for a plan never made", go,
                                 r"decision for plan never-planned that never arrived"),
                    message_case("go for a plan for another arm",
                                 go.model_copy(update={"plan_id": "stored"}),
                                 r"plan stored: joint_names .* are not the arm's"),
                    message_case("go for a plan of 2 positions a sample",
                                 go.model_copy(update={"plan_id": "narrow"}),
                                 r"plan narrow: joint_trajectory sample 0 has 2 positions, "
                                 r"the arm 6 joints")]
        if key == "wavegrasp/perception/mesh":
            flat = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]], dtype=float) * 0.05
            return [message_case("mesh of 3 vertices", ObjectMesh(
                header=header(t), shape="sphere", volume_m3=0.0, frames=1,
                **encode_mesh(flat, np.array([[0, 1, 2]]))),
                r"mesh of 3 vertices: a closed mesh needs 4")]
        if key.endswith("/joint_trajectory"):  # the same path again: followed alike
            arm = ArmModel.load(None)
            names = list(arm.jaw_joints if key.startswith("jaw/") else arm.joint_names)
            return [self.trajectory(key, "duplicate path"),
                    self.trajectory(key, "its joints in another order", names[::-1])]
        if key == "wavegrasp/planner/plan":
            narrow = example_plan("narrow", t, joints=2)
            narrow.joint_names = list(ArmModel.load(None).joint_names)
            return [message_case("duplicate plan", example_plan("stored", t)),
                    message_case("plan of 2 positions a sample", narrow)]
        return super().odd(key)

    def after(self, h: Harness) -> None:
        s = h.service
        assert s.world is not None
        assert s.world.time_s == pytest.approx(self.t_ns * 1e-9, abs=1e-3), "scene went back"
        self.frame(h)
        assert s.world.time_s == pytest.approx(self.t_ns * 1e-9, abs=1e-3)
        for kind, scale, corners in (("flat", 0.05, [[0, 0, 0], [1, 0, 0], [0, 1, 0],
                                                      [1, 1, 0]]),
                                     ("huge", 1e6, [[1, 1, 1], [1, -1, -1], [-1, 1, -1],
                                                    [-1, -1, 1]])):
            mesh = encode_mesh(np.array(corners, dtype=float) * scale,
                               np.array([[0, 1, 2], [0, 3, 1], [0, 2, 3], [1, 3, 2]]))
            h.send_msg("wavegrasp/perception/mesh", ObjectMesh(
                header=header(self.t_ns), shape="sphere", volume_m3=0.0, frames=1, **mesh))
            state = self.frame(h)  # the frame is still finished, whatever the mesh
            assert state.header.stamp_ns == pytest.approx(self.t_ns, abs=10**6), kind


class RecorderScenario(Scenario):
    name = "recorder"

    def make(self) -> Service:
        return Recorder(RecorderSettings.from_env("recorder", env=self.env,
                                                  out=self.tmp_path / "run"))

    def valid(self, key: str) -> Case:
        model = model_for_key(key)
        if model is not None:
            msg = EXAMPLES[model]()
            msg.header.stamp_ns = self.t_ns
            return message_case("valid", msg)
        if key == "tf_static":
            return Case("valid", self.sample.tf, f"{CDR};{ROS_KEYS[key]}", None)
        if key == "groundtruth/object":
            return Case("valid", self.sample.truth_cdr[0], f"{CDR};{ROS_KEYS[key]}", None,
                        attachment(0, int(self.sample.truth_ns[0])))
        if key == "clock":
            return Case("valid", encode_clock(self.t_ns), f"{CDR};{ROS_KEYS[key]}", None)
        arm = ArmModel.load(None)
        if key == "joint_states":
            names = [*arm.joint_names, *arm.jaw_joints]
            return Case("valid", joint_state_cdr(self.t_ns, names, [0.0] * len(names), []),
                        JOINT_STATE_ENC, None)
        if key.endswith("/joint_trajectory"):
            return Case("valid", trajectory_cdr(self.t_ns, list(arm.joint_names),
                                                [(0.0, list(arm.q_home))]), TRAJECTORY_ENC, None)
        if key in ROS_KEYS:  # camera frames, perception's object points
            m = self.sample.frames[0]
            return Case("valid", m.cdr, f"{CDR};{ROS_KEYS[key]}", None,
                        attachment(0, m.log_time_ns))
        return message_case("valid", EXAMPLES[FrameAck]())

    def semantic(self, key: str) -> list[Case]:
        if key in ("trisect/points", "wavegrasp/perception/points"):
            return cloud_semantic_cases(self.sample.camera_points(0), self.t_ns)
        if key == "groundtruth/object":
            return pose_semantic_cases(self.t_ns)
        arm = ArmModel.load(None)
        if key == "joint_states":
            return joint_state_semantic_cases(self.t_ns, list(arm.joint_names),
                                              list(arm.q_home))
        if key.endswith("/joint_trajectory"):
            return trajectory_semantic_cases(self.t_ns, list(arm.joint_names),
                                             list(arm.q_home))
        if key == "fuzz/unknown":
            return [Case("JSON without a schema", b"{}", JSON,
                         r"^fuzz/unknown: no message type known for this key"),
                    Case("CDR without a type", CDR_HEADER + bytes(8), CDR,
                         r"^fuzz/unknown: CDR payload without a message type")]
        return super().semantic(key)

    def odd(self, key: str) -> list[Case]:  # what is well-formed is recorded, duplicates too
        return [replace(self.valid(key), kind="duplicate")]

    def after(self, h: Harness) -> None:
        h.stop()  # writes the MCAP's summary
        kept: dict[str, int] = {}
        with (self.tmp_path / "run" / "run.mcap").open("rb") as f:
            for schema, channel, message in make_reader(f).iter_messages():
                key = channel.topic.removeprefix("/")
                kept[key] = kept.get(key, 0) + 1
                if channel.message_encoding == "json" or schema.name.startswith(
                        "wavegrasp_msgs/"):  # nothing malformed was written
                    assert decode_own(schema, channel, message) is not None, key
                else:
                    store().deserialize_cdr(message.data, schema.name)
        assert {k: kept.get(k, 0) for k in h.accepted} == h.accepted


class PlayerScenario(Scenario):
    name = "player"

    def make(self) -> Service:
        return Player(PlayerSettings.from_env("player", env=self.env,
                                              ack_services=["recorder"]),
                      open_recording(SAMPLE))

    def before(self, h: Harness) -> None:
        self.acks = 3
        h.send_msg("wavegrasp/recorder/ack", FrameAck(header=header(self.t_ns),
                                                      service="recorder", frame_seq=3))
        assert wait_until(lambda: h.service.acked_seq == 3, timeout=10)

    def odd(self, key: str) -> list[Case]:
        if key == "wavegrasp/recorder/ack":
            return [*super().odd(key), message_case("another service's ack", FrameAck(
                header=header(self.t_ns), service="gate", frame_seq=10**6))]
        return super().odd(key)

    def after(self, h: Harness) -> None:
        assert h.service.acked_seq == self.acks  # neither older nor foreign acks counted
        h.send_msg("wavegrasp/recorder/ack", FrameAck(header=header(self.t_ns),
                                                      service="recorder", frame_seq=40))
        assert wait_until(lambda: h.service.acked_seq == 40, timeout=10)


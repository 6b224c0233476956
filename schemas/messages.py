"""The messages services exchange on ``wavegrasp/...`` keys (contract: ARCHITECTURE.md).

All times are integers in nanoseconds. ``stamp_ns`` is on the recording's clock (the capture time
of the camera frame a message derives from); hop times are wall-clock ``time.time_ns()``.
Positions are metres in frame ``world`` (z up) unless a field says otherwise.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Annotated, Literal

from pydantic import BaseModel, ConfigDict, Field, field_validator

INT64_MAX = 2**63 - 1
#: Metres: a coordinate farther out is corrupt data, not a place (no grasp scene is 10 km wide).
MAX_COORDINATE_M = 1e4

#: A time in ns, as ROS, MCAP and numpy hold it: an int64 >= 0.
Nanoseconds = Annotated[int, Field(ge=0, le=INT64_MAX)]
#: A sequence number or a count: an int64 >= 0.
Count = Annotated[int, Field(ge=0, le=INT64_MAX)]
#: A coordinate, metres.
Coordinate = Annotated[float, Field(ge=-MAX_COORDINATE_M, le=MAX_COORDINATE_M)]


class Message(BaseModel):
    """Base of every message: unknown fields are kept, so newer senders stay readable.

    Floats must be finite (JSON ``NaN`` / ``Infinity`` and numbers too big for a double are
    refused), times and counts fit an int64, coordinates are within ``MAX_COORDINATE_M``.
    """

    model_config = ConfigDict(extra="allow", allow_inf_nan=False)


class Hop(Message):
    """One service's passage: when it received the input and when it sent its output."""

    service: str
    recv_ns: Nanoseconds = Field(description="wall clock, ns, when the input arrived")
    sent_ns: Nanoseconds = Field(
        0, description="wall clock, ns, when the output left (0 until sent)")


class Header(Message):
    """Sequence, capture stamp, frame and the trace of every hop the data went through."""

    seq: Count = 0
    stamp_ns: Nanoseconds = Field(
        0, description="recording clock, ns: capture time of the source frame")
    frame_id: str = "world"
    trace: list[Hop] = Field(default_factory=list)


class Vec3(Message):
    x: Coordinate
    y: Coordinate
    z: Coordinate

    @classmethod
    def of(cls, v: Sequence[float]) -> Vec3:
        """From an array of shape (3,)."""
        return cls(x=float(v[0]), y=float(v[1]), z=float(v[2]))


class Quaternion(Message):
    x: float = 0.0
    y: float = 0.0
    z: float = 0.0
    w: float = 1.0


class Pose(Message):
    position: Vec3
    orientation: Quaternion = Field(default_factory=Quaternion)


class ObjectObservation(Message):
    """``wavegrasp/perception/object``: the tracked object's volume centroid in one frame.

    ``centroid`` is None when the frame holds no usable observation; ``reason`` then says why.
    """

    header: Header
    centroid: Vec3 | None = None
    points_used: Count = 0
    quality: float = Field(0.0, ge=0.0, le=1.0, description="0 = unusable, 1 = best")
    sigma_m: float | None = Field(None, ge=0.0,
                                  description="1-sigma centroid uncertainty, metres")
    reason: str | None = None
    shape: Literal["sphere", "cylinder", "box", "revolution"] | None = None
    axis: Vec3 | None = Field(None, description="unit symmetry axis, world (cylinder)")
    radius_m: float | None = Field(None, gt=0.0, le=MAX_COORDINATE_M)
    length_m: float | None = Field(None, gt=0.0, le=MAX_COORDINATE_M)
    axial_offset_m: float | None = Field(None, ge=-MAX_COORDINATE_M, le=MAX_COORDINATE_M,
                                         description="the middle of its length lies this far "
                                         "along axis from the centroid (a bottle's neck moves "
                                         "the centroid towards its body); None: at it")
    fit_rms_m: float | None = Field(None, ge=0.0, description="RMS distance of points to the shape")
    side: Vec3 | None = Field(None, description="a box: unit direction across its axis of its "
                              "thinner extent, world")
    side_width_m: float | None = Field(None, gt=0.0, le=MAX_COORDINATE_M,
                                       description="a box: its extent along side")
    breadth_m: float | None = Field(None, gt=0.0, le=MAX_COORDINATE_M,
                                    description="a box: its extent across both axis and side")
    seabed_normal: Vec3 | None = Field(None, description="the seabed plane seen in the cloud: "
                                       "its unit normal towards the water, world; None: not "
                                       "seen")
    seabed_offset_m: float | None = Field(None, ge=-MAX_COORDINATE_M, le=MAX_COORDINATE_M,
                                          description="the seabed plane: the points p with "
                                          "seabed_normal . p + seabed_offset_m = 0")


class ObjectMesh(Message):
    """``wavegrasp/perception/mesh``: the object's closed mesh, accumulated over many frames.

    Vertices are little-endian float32 x, y, z in metres in the object's own frame (origin at
    the volume centroid, z along the symmetry axis); triangles are little-endian uint32 vertex
    indices, counter-clockwise seen from outside; both base64-encoded.
    """

    header: Header
    shape: Literal["sphere", "cylinder", "box", "revolution"]
    vertices_b64: str
    triangles_b64: str
    vertex_count: Count
    triangle_count: Count
    volume_m3: float
    frames: Count = Field(description="camera frames accumulated into the mesh")


class PredictionSample(Message):
    t_ns: Nanoseconds = Field(description="recording clock, ns")
    x: Coordinate
    y: Coordinate
    z: Coordinate
    sigma: float = Field(ge=0.0, description="1-sigma position error expected at t_ns, metres")


def check_increasing(samples: list, field: str) -> list:
    """``samples`` (each with a ``t_ns``) if their times strictly increase; else ValueError
    naming the ``field`` and the first sample out of order."""
    for k in range(1, len(samples)):
        if samples[k].t_ns <= samples[k - 1].t_ns:
            raise ValueError(f"{field} not strictly increasing in t_ns at sample {k}")
    return samples


class MotionPrediction(Message):
    """``wavegrasp/predictor/prediction``: samples from now to at least one period ahead."""

    header: Header
    model: str
    period_s: float = Field(gt=0.0)
    samples: list[PredictionSample]
    parameters: dict[str, float] = Field(default_factory=dict)
    warm: bool = Field(True, description="False while the model is still warming up")

    @field_validator("samples")
    @classmethod
    def check_sample_times(cls, samples: list[PredictionSample]) -> list[PredictionSample]:
        return check_increasing(samples, "samples")


class JointSample(Message):
    t_ns: Nanoseconds
    positions: list[float] = Field(description="radians (revolute), metres (jaw)")
    velocities: list[float] = Field(default_factory=list)


class CartesianSample(Message):
    t_ns: Nanoseconds
    x: Coordinate
    y: Coordinate
    z: Coordinate


class GraspPlan(Message):
    """``wavegrasp/planner/plan``: a grasp at ``t_grasp_ns`` and the timed path to reach it."""

    header: Header
    plan_id: str
    t_start_ns: Nanoseconds
    t_grasp_ns: Nanoseconds
    grasp: Pose
    approach: Vec3 = Field(description="unit approach direction, world")
    joint_names: list[str] = Field(default_factory=list)
    joint_trajectory: list[JointSample] = Field(default_factory=list)
    cartesian_path: list[CartesianSample] = Field(default_factory=list)
    confidence: float = 0.0
    waypoints: list[Vec3] = Field(default_factory=list,
                                  description="P_init, the P_i, the pre-grasp point, P_f; world")
    t_final_ns: Nanoseconds | None = Field(None, description="when the final move into P_f begins")
    jaw_preshape_m: float | None = Field(
        None, description="the jaw's opening for the final move, a little wider than the object")
    t_close_ns: Nanoseconds | None = Field(
        None, description="when the jaw starts closing, so it meets the object at t_grasp_ns")
    candidates: list[Pose] = Field(
        default_factory=list, description="grasp poses checked in full for this plan, in "
        "order, the chosen one last; world")
    standby: list[float] = Field(
        default_factory=list, description="joint positions, in joint_names' order, the arm "
        "returns to after the attempt: its home pose turned to face the object; empty: its "
        "home pose")
    update_of: str | None = Field(
        None, description="closed-loop execution: this plan moves the executing plan of this "
        "plan_id to a newer prediction; its joint_trajectory starts where it takes over (the "
        "arm splices it in) and ends at the grasp")
    t_contact_ns: Nanoseconds | None = Field(
        None, description="closed-loop update: when, on the prediction it was made from, the "
        "arm would first touch the object before the final move; None: it keeps clear")

    @field_validator("joint_trajectory")
    @classmethod
    def check_trajectory_times(cls, samples: list[JointSample]) -> list[JointSample]:
        return check_increasing(samples, "joint_trajectory")


class ArmStandby(Message):
    """``wavegrasp/planner/standby``: a move of the idle arm to where it waits, asked for
    when no grasp can be planned from where it is (an arm that starts facing away); timed
    from ``t_start_ns`` and checked clear of the object's predicted path. Not a grasp: the
    arm takes it only while it executes nothing."""

    header: Header
    t_start_ns: Nanoseconds
    joint_names: list[str]
    joint_trajectory: list[JointSample] = Field(description="from the arm's pose to standby, "
                                                "at rest at both ends")
    reason: str = ""


class GateDecision(Message):
    """``wavegrasp/gate/decision``: go only while recent prediction error stays within bounds."""

    header: Header
    plan_id: str
    go: bool
    mean_error_m: float | None = Field(ge=0.0)
    threshold_m: float
    window_s: float
    reason: str = ""
    failed: list[str] = Field(default_factory=list,
                              description="the checks that said no (empty when go)")
    matches: Count = Field(0, description="predictions matched against observations in the "
                           "window")
    latency_s: float | None = Field(None, ge=0.0, description="the plan's age when decided, "
                                    "recording seconds: its data's capture to now")


class DecisionLatency(Message):
    """``wavegrasp/scene/latency``: where a gate decision's milliseconds went, read from its
    trace (wall clock): each service's time in hand (``perception``) and each transfer
    (``perception -> predictor``), then camera frame to decision; for plots of the latency
    per hop (Foxglove: ``hops_ms[:]{key=="planner"}.value``)."""

    header: Header
    plan_id: str
    go: bool
    hops_ms: dict[str, float] = Field(default_factory=dict, description="per hop, in the "
                                      "trace's order, milliseconds")
    total_ms: float = Field(description="the camera frame's publication to the decision, ms")


FailureKind = Literal["prediction", "collision", "timing", "abrupt_change", "unreachable", "other"]


class GateAbort(Message):
    """``wavegrasp/gate/abort``: stop executing plan ``plan_id`` and retreat (closed-loop
    execution), with the reason and the figure that passed its limit."""

    header: Header
    plan_id: str
    reason: str
    value: float | None = Field(None, description="the figure past its limit: an error (m), an "
                                "input's age (s) or the time to a contact ahead (s, under it)")
    limit: float | None = None


class GraspOutcome(Message):
    """``wavegrasp/sim/outcome``: one attempt's result and the evidence that decided it."""

    header: Header
    plan_id: str
    trial: Count
    attempt: Count
    success: bool
    failure: FailureKind | None = None
    evidence: dict[str, float | str | bool] = Field(default_factory=dict)
    aborted: bool = Field(False, description="the gate aborted the attempt (evidence: its "
                          "reason); not a failure of the paper's kinds")


class ArmState(Message):
    """``wavegrasp/sim/arm_state``: the arm's joints and jaw, from the sim or an arm driver."""

    header: Header
    joint_names: list[str]
    positions: list[float]
    velocities: list[float] = Field(default_factory=list)
    jaw_opening_m: float = 0.0
    executing_plan_id: str | None = None
    returning: bool = Field(False, description="moving back to its standby after an attempt "
                            "(or to the one the planner asked for): not idle, though it may "
                            "be at rest the moment the move begins")


class Clock(Message):
    """``wavegrasp/clock``: the recording's time, published by the player."""

    header: Header
    rate: float = Field(1.0, ge=0.0,
                        description="recording seconds per wall second; 0 = as fast")
    published: dict[str, Count] = Field(
        default_factory=dict, description="CDR messages the player has published so far, per "
        "key: a service that needs all of them before it finishes a frame waits for them")


class FrameAck(Message):
    """``wavegrasp/<service>/ack``: the service has finished camera frame ``frame_seq``.

    The player waits for it in lockstep pacing (and for the last frame in every pacing).
    """

    header: Header
    service: str
    frame_seq: Count


class Heartbeat(Message):
    """``wavegrasp/gate/heartbeat``: the gate is there and its link to the arm holds. Sent
    every ``period_s`` (wall) while the recording plays in real time; the arm's side stops
    and holds when it misses them (the arm's watchdog)."""

    header: Header
    period_s: float = Field(gt=0, description="wall seconds between two heartbeats")


class PlayerStatus(Message):
    """``wavegrasp/player/status``: what the player is replaying and how far it got."""

    header: Header
    state: Literal["starting", "playing", "finished", "failed"]
    recording: str
    pace: str
    frames: Count = 0
    messages: Count = 0
    metadata: dict[str, str] = Field(default_factory=dict)
    error: str | None = None


class ServiceStats(Message):
    """``wavegrasp/<service>/stats``: counters every service publishes each second and at exit."""

    header: Header
    service: str
    subscriptions: list[str] = Field(default_factory=list)
    received: dict[str, Count] = Field(default_factory=dict)
    received_shared: dict[str, Count] = Field(
        default_factory=dict, description="of those received, how many came through zenoh's "
        "shared memory (from a process on this host), per key")
    pool_full: dict[str, Count] = Field(
        default_factory=dict, description="large messages sent over the link, not through "
        "shared memory, because this process's pool was full (receivers still held its "
        "earlier ones), per key")
    bad: dict[str, Count] = Field(default_factory=dict)
    last_bad_reason: dict[str, str] = Field(default_factory=dict)
    counters: dict[str, Count] = Field(default_factory=dict,
                                       description="service-specific counts")
    uptime_s: float = Field(0.0, ge=0.0)
    cpu_s: float = Field(0.0, ge=0.0, description="the process's CPU time so far, user and "
                         "system, all its threads, seconds (from its start, or its fork)")

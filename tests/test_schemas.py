"""Message contracts: exported JSON Schema is current; every model round-trips through JSON."""

from __future__ import annotations

import json

import pytest

from wavegrasp.schemas import (
    KEY_TYPES,
    MESSAGE_TYPES,
    FrameAck,
    GraspOutcome,
    Header,
    Hop,
    ObjectObservation,
    ServiceStats,
    Vec3,
    model_for_key,
)
from wavegrasp.schemas.export import JSON_DIR, schema_path, schema_text


@pytest.mark.parametrize("name", sorted(MESSAGE_TYPES))
def test_exported_schema_is_current(name: str) -> None:
    path = schema_path(name)
    assert path.exists(), f"{path} missing: run python -m wavegrasp.schemas.export"
    assert path.read_text() == schema_text(name), (
        f"{path} is out of date: run python -m wavegrasp.schemas.export")


def test_no_stale_schema_files() -> None:
    on_disk = {p.name for p in JSON_DIR.glob("*.schema.json")}
    assert on_disk == {schema_path(n).name for n in MESSAGE_TYPES}


def test_contract_fields_present() -> None:
    fields = {name: set(model.model_json_schema()["properties"])
              for name, model in MESSAGE_TYPES.items()}
    assert {"header", "centroid", "points_used", "quality", "reason"} <= fields[
        "ObjectObservation"]
    assert {"header", "model", "period_s", "samples"} <= fields["MotionPrediction"]
    assert {"header", "plan_id", "t_start_ns", "t_grasp_ns", "grasp", "approach",
            "joint_trajectory", "cartesian_path", "confidence"} <= fields["GraspPlan"]
    assert {"header", "plan_id", "go", "mean_error_m", "threshold_m", "window_s",
            "reason"} <= fields["GateDecision"]
    assert {"header", "plan_id", "trial", "attempt", "success", "failure",
            "evidence"} <= fields["GraspOutcome"]


def test_json_round_trip_keeps_trace() -> None:
    msg = ObjectObservation(
        header=Header(seq=3, stamp_ns=10**18, trace=[Hop(service="perception", recv_ns=5,
                                                         sent_ns=9)]),
        centroid=Vec3(x=0.1, y=-0.2, z=0.3), points_used=1200, quality=0.9)
    back = ObjectObservation.model_validate_json(msg.model_dump_json())
    assert back == msg
    assert back.header.trace[0].sent_ns == 9


def test_unknown_fields_survive_so_contracts_can_grow() -> None:
    data = json.loads(FrameAck(header=Header(), service="gate", frame_seq=4).model_dump_json())
    data["added_later"] = 1
    assert FrameAck.model_validate(data).model_dump()["added_later"] == 1


def test_failure_kind_is_closed() -> None:
    with pytest.raises(ValueError, match="failure"):
        GraspOutcome(header=Header(), plan_id="p", trial=0, attempt=1, success=False,
                     failure="bad luck")


def test_keys_map_to_models() -> None:
    for key, model in KEY_TYPES.items():
        assert model_for_key(key) is model
    assert model_for_key("wavegrasp/gate/stats") is ServiceStats
    assert model_for_key("wavegrasp/gate/ack") is FrameAck
    assert model_for_key("trisect/points") is None


def test_a_plan_whose_samples_do_not_move_on_in_time_is_refused() -> None:
    """Two samples of an arm's trajectory at one time cannot be followed: refused where the
    plan is made or read, naming the field and the sample."""
    from wavegrasp.schemas import GraspPlan, Pose, Quaternion

    def plan(times: list[int]) -> GraspPlan:
        return GraspPlan(header=Header(), plan_id="p", t_start_ns=1, t_grasp_ns=9,
                         grasp=Pose(position=Vec3(x=0, y=0, z=0),
                                    orientation=Quaternion(x=0, y=0, z=0, w=1)),
                         approach=Vec3(x=0, y=0, z=-1), joint_names=["a"],
                         joint_trajectory=[{"t_ns": t, "positions": [0.0]} for t in times])

    assert len(plan([1, 2, 3]).joint_trajectory) == 3
    with pytest.raises(ValueError, match="joint_trajectory not strictly increasing in t_ns "
                                         "at sample 2"):
        plan([1, 2, 2])

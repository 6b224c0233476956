"""Scenarios: what a recording depends on, validated, and recorded from a file."""

from __future__ import annotations

import json
import os
import subprocess
from pathlib import Path

import numpy as np
import pytest
import yaml
from scipy.spatial.transform import Rotation

from wavegrasp.ops.suite import recording_seconds
from wavegrasp.recording_io.reader import open_recording
from wavegrasp.recording_io.ros_msgs import decode_tf
from wavegrasp.wavetank.record import RecordConfig, generate, main
from wavegrasp.wavetank.scenario import (
    NAMED,
    MountSpec,
    Scenario,
    SeaSpec,
    default_arm,
    load_scenario,
    paper_scenario,
)
from wavegrasp.wavetank.suite import draw_scenarios, reach_verdict

from conftest import source_frames, wavegrasp_cmd

SPHERE = {"sea": {"height_m": 0.2, "period_s": 2.0},
          "object": {"family": "sphere", "diameter_m": 0.15, "mass_kg": 0.4}}


def write(tmp_path: Path, doc: dict, name: str = "s.yaml") -> Path:
    path = tmp_path / name
    path.write_text(yaml.safe_dump(doc))
    return path


@pytest.mark.parametrize(("change", "problem"), [
    ({"mount": {"position": [0.0, 0.6, 1.2]}}, "mount.position: z = 1.2 m is out of the water"),
    ({"mount": {"position": [1.5, 0.6, 0.4]}}, "beyond its 1.000 m reach"),
    ({"camera": {"eye": [0.0, 0.05, 0.52]}}, "camera.eye: inside or touching the object"),
    ({"object": {"family": "cylinder", "diameter_m": 0.1, "mass_kg": 0.3}},
     "object: length_m: a cylinder needs one"),
    ({"object": {**SPHERE["object"], "rest_height_m": 0.9}}, "is not under water 0.93 m deep"),
    ({"sea": {"height_m": 0.2, "period_s": 2.0, "colour": "blue"}}, "sea.colour: Extra inputs"),
    ({"camera": {"rate_hz": -3}}, "camera.rate_hz: Input should be greater than 0"),
])
def test_a_scenario_that_cannot_be_is_refused_in_one_line(tmp_path: Path, change: dict,
                                                          problem: str) -> None:
    path = write(tmp_path, {**SPHERE, **change})
    with pytest.raises(ValueError) as err:
        load_scenario(path)
    text = str(err.value)
    assert text.startswith(f"{path}: ") and problem in text and "\n" not in text, text


def test_the_papers_twelve_configurations_are_named_scenarios() -> None:
    assert len(NAMED) == 12
    s = load_scenario("paper-w1-buoy")
    assert (s.sea.height_m, s.sea.period_s, s.object.family) == (0.25, 1.25, "sphere")
    assert load_scenario("paper-w3-bottle").object.length_m == pytest.approx(0.16)
    # A file holds the same scenario as its name.
    assert Scenario(**json.loads(s.model_dump_json())) == s


def test_a_paper_scenario_records_what_its_flags_recorded(tmp_path: Path) -> None:
    """Today's flags are named scenarios: the same messages, byte for byte."""
    flags = RecordConfig(wave=2, object="can_half", seconds=1.0, seed=3, preroll_s=1.0)
    generate(flags, tmp_path / "flags.mcap")
    named = paper_scenario(2, "can_half", seconds=1.0, seed=3, preroll_s=1.0)
    generate(named, tmp_path / "named.mcap")
    assert source_frames(tmp_path / "flags.mcap") == source_frames(tmp_path / "named.mcap")


def test_record_scenario_places_the_mount_and_camera_where_the_file_says(
        tmp_path: Path) -> None:
    doc = {**SPHERE, "name": "sideways",
           "mount": {"position": [0.0, 0.6, 0.45], "yaw_offset_deg": 90},
           "camera": {"eye": [1.0, 0.3, 0.7], "rate_hz": 15, "width": 160, "height": 120},
           "seconds": 2, "preroll_s": 1}
    out = tmp_path / "sideways.mcap"
    assert main(["--scenario", str(write(tmp_path, doc)), "--out", str(out)]) == 0
    messages = list(open_recording(out).messages())
    frames = [m for m in messages if m.topic == "/trisect/points"]
    assert len(frames) == 30  # 15 Hz for 2 s
    tf = {child: T for _, child, T in decode_tf(next(m for m in messages
                                                     if m.topic == "/tf_static").cdr)}
    mount = tf["bravo_base_link"]
    assert np.allclose(mount[:3, 3], [0.0, 0.6, 0.45])
    # Facing the object (yaw -90 deg) turned by 90 deg: the arm faces +x, the object on its right.
    yaw = Rotation.from_matrix(mount[:3, :3]).as_euler("xyz")[2]
    assert yaw == pytest.approx(0.0, abs=1e-9)
    assert np.allclose(tf["trisect_optical"][:3, 3], [1.0, 0.3, 0.7])


def test_random_scenarios_are_deterministic_and_span_the_documented_ranges() -> None:
    scenarios, refused = draw_scenarios(40, seed=0)
    again, _ = draw_scenarios(40, seed=0)
    assert scenarios == again and len(scenarios) == 40
    assert all(": " in r and "\n" not in r for r in refused)  # each redraw says why
    arm = default_arm()
    for s in scenarios:
        yaw = s.mount_yaw()
        c, sn = np.cos(yaw), np.sin(yaw)
        shoulder = np.asarray(s.mount.position) + np.array(
            [[c, -sn, 0], [sn, c, 0], [0, 0, 1]]) @ arm.shoulder
        assert 0.4 - 1e-3 <= np.linalg.norm(shoulder - s.rest) <= 0.85 + 1e-3, s.name
        assert -0.4 - 1e-3 <= shoulder[2] - s.rest[2] <= 0.2 + 1e-3, s.name
        assert 0.5 - 1e-3 <= np.linalg.norm(np.asarray(s.camera.eye) - s.rest) <= 1.6 + 1e-3
        assert 0.8 <= s.sea.period_s <= 2.5 and 0.05 <= s.sea.height_m <= 0.35
        assert 5 <= s.camera.rate_hz <= 30
        size = s.object.diameter_m
        round_ = s.object.family in ("sphere", "ellipsoid")
        assert 0.06 <= size <= 0.18 if round_ else 0.04 <= size <= 0.12
    families = {s.object.family for s in scenarios}
    turned = [abs(s.mount.yaw_offset_deg) > 90 for s in scenarios]
    assert families == {"sphere", "cylinder", "ellipsoid", "box", "bottle"}
    assert any(turned) and not all(turned)


def test_random_seas_are_drawn_of_the_kinds_asked_for_and_the_rest_unchanged() -> None:
    regular, _ = draw_scenarios(12, seed=5)
    both, _ = draw_scenarios(12, seed=5, seas=("regular", "jonswap"))
    assert {s.sea.kind for s in regular} == {"regular"}
    assert {s.sea.kind for s in both} == {"regular", "jonswap"}
    # The kind is drawn on its own: every other parameter is the regular suite's.
    for r, b in zip(regular, both, strict=True):
        assert b.model_copy(update={"sea": b.sea.model_copy(update={"kind": "regular"})}) == r
    with pytest.raises(ValueError, match="unknown choppy; known regular, jonswap"):
        draw_scenarios(1, seed=5, seas=("regular", "choppy"))


def test_reach_is_judged_from_the_arm_model_over_the_whole_swing() -> None:
    near = paper_scenario(2, "buoy")
    assert reach_verdict(near) is None
    # The same mount, the object now swinging in a sea twice as high and slower.
    far = paper_scenario(2, "buoy", mount=MountSpec(position=(0.55, -0.55, 0.45)),
                         sea=SeaSpec(height_m=0.35, period_s=2.5))
    assert "beyond the arm's" in (reach_verdict(far) or "")


def test_eval_suite_random_runs_drawn_scenarios_and_reports_them_by_factor(
        tmp_path: Path) -> None:
    out, cache = tmp_path / "suite", tmp_path / "cache"
    result = subprocess.run(wavegrasp_cmd(
        "eval", "--suite", "random", "--scenarios", "2", "--seed", "3", "--trials", "1",
        "--jobs", "2", "--discard-recordings", "--out", str(out)), capture_output=True,
        text=True, timeout=900, env={**os.environ, "WAVEGRASP_CACHE": str(cache)})
    assert result.returncode == 0, result.stdout[-3000:] + result.stderr[-3000:]
    # Each recording was generated for its runs and is gone after them.
    assert "generating" in result.stderr and not list(cache.rglob("*.mcap"))
    report = json.loads((out / "report.json").read_text())
    drawn, _ = draw_scenarios(2, 3, seconds=recording_seconds(1, 3))
    ran = [r["scenario"] for r in report["runs"]]
    # Every drawn scenario is either run or listed with the reason it was not.
    assert sorted(ran + list(report["out_of_reach"])) == sorted(s.name for s in drawn)
    for run in report["runs"]:
        assert run["exit_code"] == 0 and run["trials"] == 1
        assert set(run["factors"]) >= {"mount bearing (deg)", "object", "period (s)", "cloud"}
    # The pipeline really ran: random-3-000 (a bottle) is planned on.
    assert report["runs"][0]["scenario"] == "random-3-000" and report["runs"][0]["planned_on"] > 0
    if ran:
        assert set(report["by_factor"]["blend"]) == set(report["runs"][0]["factors"])
        assert (out / "by_factor.png").stat().st_size > 0
    assert "seed 3" in (out / "report.md").read_text()

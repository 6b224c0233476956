"""The wave tank: linear wave physics, the tethered body, and conformance of its recordings."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest

from wavegrasp.recording_io.reader import open_recording
from wavegrasp.recording_io.typestore import ros2_typestore
from wavegrasp.wavetank.analysis import dominant_period
from wavegrasp.wavetank.body import OBJECTS, TetheredBody
from wavegrasp.wavetank.record import RecordConfig, main, simulate, slack_warning
from wavegrasp.wavetank.scenario import TANK_DEPTH_M as DEPTH_M
from wavegrasp.wavetank.waves import (
    TABLE_I,
    G,
    Sea,
    Sway,
    orbital_amplitudes,
    regular_sea,
    wavenumber,
)

from conftest import make_recording


def test_dispersion_relation_against_known_values() -> None:
    # 10 s waves in 10 m of water are 92.3 m long (the Shore Protection Manual's example).
    assert 2 * np.pi / wavenumber(2 * np.pi / 10, 10.0) == pytest.approx(92.3, abs=0.1)
    # Limits: deep water k = ω²/g, shallow water k = ω/√(gh).
    assert wavenumber(6.0, 50.0) == pytest.approx(36 / G, rel=1e-6)
    assert wavenumber(0.2, 0.5) == pytest.approx(0.2 / np.sqrt(G * 0.5), rel=1e-2)


def test_orbital_velocity_decays_with_depth_as_linear_theory_says() -> None:
    cond = TABLE_I[1]
    omega, k = 2 * np.pi / cond.period_s, wavenumber(2 * np.pi / cond.period_s, DEPTH_M)
    heights = np.linspace(0.05, DEPTH_M, 10)
    u, w = np.array([orbital_amplitudes(cond.height_m, cond.period_s, DEPTH_M, z)
                     for z in heights]).T
    assert np.all(np.diff(u) > 0) and np.all(np.diff(w) > 0)
    assert u[-1] == pytest.approx(cond.height_m / 2 * omega / np.tanh(k * DEPTH_M))
    # The Sea's kinematics give the same amplitudes at any height.
    sea = Sea(depth=DEPTH_M, amplitudes=np.array([cond.height_m / 2]), omegas=np.array([omega]),
              directions=np.zeros(1), phases=np.zeros(1))
    ts = np.linspace(0, cond.period_s, 200, endpoint=False)
    flow = np.array([sea.kinematics(t, np.array([0.0, 0.0, 0.3]))[0] for t in ts])
    u3, w3 = orbital_amplitudes(cond.height_m, cond.period_s, DEPTH_M, 0.3)
    assert np.abs(flow[:, 0]).max() == pytest.approx(u3, rel=1e-3)
    assert np.abs(flow[:, 2]).max() == pytest.approx(w3, rel=1e-3)


@pytest.mark.parametrize("wave", [1, 2])
def test_table_i_rows_1_and_2_are_reproduced_at_the_object(wave: int) -> None:
    cond = TABLE_I[wave]
    u, w = orbital_amplitudes(cond.height_m, cond.period_s, DEPTH_M, 0.525)
    assert u == pytest.approx(cond.max_horizontal_mps, rel=0.10)
    assert w == pytest.approx(cond.max_vertical_mps, rel=0.10)


@pytest.mark.parametrize("wave", sorted(TABLE_I))
@pytest.mark.parametrize("obj", sorted(OBJECTS))
def test_motion_follows_the_wave_period_on_a_constant_tether(wave: int, obj: str) -> None:
    traj = simulate(RecordConfig(wave=wave, object=obj, seconds=30.0, seed=1, preroll_s=20.0))
    period = dominant_period(traj.times_s, traj.positions)
    assert period == pytest.approx(TABLE_I[wave].period_s, rel=0.02)
    reach = np.linalg.norm(traj.positions, axis=1)  # the anchor is the world origin
    assert np.ptp(reach) < 1e-9, "the centroid stays on the tether's sphere"
    assert traj.slack_fraction == 0.0
    assert np.ptp(traj.positions[:, 0]) > 0.02, "the waves move the object"


def test_empty_and_half_full_can_move_differently() -> None:
    amp = {}
    for obj in ("can_empty", "can_half"):
        traj = simulate(RecordConfig(wave=2, object=obj, seconds=20.0, seed=0, preroll_s=20.0))
        amp[obj] = np.ptp(traj.positions[:, 0])
    assert amp["can_empty"] > 1.3 * amp["can_half"]


def test_neutrally_buoyant_body_leaves_the_tether_slack(tmp_path: Path, capsys) -> None:
    can = OBJECTS["can_half"]
    neutral = dataclasses.replace(can, mass=1000.0 * can.volume)
    sea = regular_sea(TABLE_I[1], DEPTH_M, np.random.default_rng(0))
    body = TetheredBody(neutral, sea, np.zeros(3), 0.4)
    for i in range(10000):
        body.step(i * 0.002, 0.002)
    assert body.slack_fraction > 0.2
    assert np.linalg.norm(body.p) <= body.radius + 1e-12, "slack, never stretched"
    warning = slack_warning("neutral can", body.slack_fraction)
    assert warning is not None and "not buoyant enough" in warning
    # A buoyant object's recording carries no such warning.
    assert main(["--wave", "1", "--object", "can_half", "--seconds", "0.5",
                 "--out", str(tmp_path / "ok.mcap")]) == 0
    assert "slack" not in capsys.readouterr().err


def test_still_water_swing_loses_energy() -> None:
    """Displaced in still water, a buoyant body swings back and its energy only decays."""
    still = Sea(depth=DEPTH_M, amplitudes=np.zeros(1), omegas=np.ones(1), directions=np.zeros(1),
                phases=np.zeros(1), sway=Sway())
    body = TetheredBody(OBJECTS["buoy"], still, np.zeros(3), 0.465)
    angle = np.deg2rad(20)
    body.p = body.radius * np.array([np.sin(angle), 0.0, np.cos(angle)])
    energy = []
    for i in range(5000):
        body.step(i * 0.002, 0.002)
        if i % 50 == 0:  # potential of net buoyancy + kinetic energy of the inertial mass
            energy.append(-body.spec.net_buoyancy * body.p[2]
                          + 0.5 * body.inertial_mass * body.v @ body.v)
    assert np.all(np.diff(energy) <= 1e-9)
    assert abs(body.p[0]) < 0.2 * body.radius * np.sin(angle)


def test_recording_conforms_to_the_contract(tmp_path: Path) -> None:
    path = make_recording(tmp_path / "rec.mcap", seconds=2.0, seed=4, wave=2, object="bottle")
    again = make_recording(tmp_path / "again.mcap", seconds=2.0, seed=4, wave=2, object="bottle")
    assert path.read_bytes() == again.read_bytes(), "the same seed gives the same file"
    rec = open_recording(path)
    assert rec.metadata["wave"] == "2" and rec.metadata["object"] == "bottle"
    store = ros2_typestore()
    last: dict[str, int] = {}
    counts: dict[str, int] = {}
    gt = {}
    tf = {}
    clouds = []
    for m in rec.messages():
        assert m.log_time_ns > last.get(m.topic, -1), f"{m.topic} stamps must increase"
        last[m.topic] = m.log_time_ns
        counts[m.topic] = counts.get(m.topic, 0) + 1
        msg = store.deserialize_cdr(m.cdr, m.msgtype)
        if m.topic == "/groundtruth/object":
            assert msg.header.frame_id == "world"
            assert msg.header.stamp.sec * 10**9 + msg.header.stamp.nanosec == m.log_time_ns
            gt[m.log_time_ns] = np.array([msg.pose.position.x, msg.pose.position.y,
                                          msg.pose.position.z])
        elif m.topic == "/tf_static":
            tf = {t.child_frame_id: t for t in msg.transforms}
            assert {t.header.frame_id for t in msg.transforms} == {"world"}
        else:
            assert msg.header.frame_id == "trisect_optical" and msg.point_step == 12
            assert [f.name for f in msg.fields] == ["x", "y", "z"]
            clouds.append((m.log_time_ns, np.frombuffer(msg.data, "<f4").reshape(-1, 3)))
    assert counts == {"/trisect/points": 20, "/groundtruth/object": 200, "/tf_static": 2}
    assert set(tf) == {"trisect_optical", "bravo_base_link"}
    assert all(20_000 <= len(c) <= 60_000 for _, c in clouds)
    # Taken to world with tf_static, the cloud holds the object's surface around ground truth.
    from scipy.spatial.transform import Rotation

    cam = tf["trisect_optical"].transform
    rot = Rotation.from_quat([cam.rotation.x, cam.rotation.y, cam.rotation.z, cam.rotation.w])
    eye = np.array([cam.translation.x, cam.translation.y, cam.translation.z])
    stamp, cloud = clouds[5]
    world = rot.apply(cloud.astype(float)) + eye
    near = np.linalg.norm(world - gt[stamp], axis=1) < OBJECTS["bottle"].length / 2 + 0.005
    assert near.sum() > 150
    assert (world[~near, 2] < 0.01).mean() > 0.9, "the rest is mostly seabed (z = 0)"

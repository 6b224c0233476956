"""``wavegrasp up --tether MBIT``: the vehicle's services in a network namespace of their own,
joined to the topside's by a shaped veth pair, router to router; the run grasps across it and
its traffic is counted on the link."""

from __future__ import annotations

import json
import os
import subprocess
from pathlib import Path

import pytest

from conftest import make_recording, recorded, source_frames, wavegrasp_cmd

pytestmark = pytest.mark.skipif(os.geteuid() != 0, reason="network namespaces need root")


def test_a_run_across_a_tether_grasps_and_the_link_carries_the_camera(tmp_path: Path) -> None:
    rec = make_recording(tmp_path / "can.mcap", seconds=16.0, seed=3, wave=2, object="can_half")
    out = tmp_path / "run"
    result = subprocess.run(wavegrasp_cmd("up", str(rec), "--tether", "100", "--out", str(out)),
                            capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, result.stdout[-3000:]
    assert "network namespace" in result.stdout
    summary = json.loads((out / "summary.json").read_text())
    assert summary["exit_codes"]["vehicle-router"] == 0
    assert summary["outcomes"] and summary["outcomes"][0]["success"], summary["outcomes"]
    assert not summary["bad_messages"]
    # Every camera frame crossed the link (no shared memory around it), bit-identical; the
    # clouds are the most of it: 160 frames of about 0.44 MB in about 16 s, ~35 Mbit/s up.
    payloads, _ = recorded(out / "run.mcap")
    assert payloads["/trisect/points"] == source_frames(rec)
    traffic = summary["tether"]
    assert traffic["mbit"] == 100
    assert 25 < traffic["up_mean_mbit_s"] < traffic["up_peak_mbit_s"] <= 100 * 1.05
    assert 0 < traffic["down_mean_mbit_s"] < 5
    names = subprocess.run(["ip", "netns", "list"], capture_output=True, text=True).stdout
    assert "wgt" not in names  # the namespace went with the run


def test_a_tether_needs_a_bandwidth(tmp_path: Path) -> None:
    done = subprocess.run(wavegrasp_cmd("up", "--tether", "0", "--out", str(tmp_path)),
                          capture_output=True, text=True, timeout=60)
    assert done.returncode == 2 and "--tether 0: the bandwidth must be > 0" in done.stderr

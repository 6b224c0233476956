"""``docker-compose up``, for real: ops/compose-test.sh builds the image from ops/Dockerfile and
runs docker-compose.yml's services in containers on a recording, as a user would.

Needs root (to install Docker and start dockerd, as CI does) or a Docker engine it may use.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
from pathlib import Path

import pytest

from wavegrasp.ops.keys import LOGINS

from conftest import ROOT, make_recording, recorded, source_frames


def docker_usable() -> bool:
    if os.geteuid() == 0:
        return True  # compose-test.sh installs Docker and starts dockerd itself
    docker = shutil.which("docker")
    return bool(docker) and subprocess.run([docker, "info"], capture_output=True).returncode == 0


pytestmark = pytest.mark.skipif(not docker_usable(),
                                reason="needs root or a Docker engine this user may use")


@pytest.fixture(scope="module")
def compose_run(tmp_path_factory: pytest.TempPathFactory):
    """One build and one ``docker-compose up`` (lockstep) on a 16 s recording of a can."""
    tmp = tmp_path_factory.mktemp("docker")
    (tmp / "recordings").mkdir()
    rec = make_recording(tmp / "recordings" / "can.mcap", seconds=16.0, seed=3, wave=2,
                         object="can_half")
    out = tmp / "runs" / "docker"
    out.mkdir(parents=True)
    if os.geteuid() == 0:  # a folder of someone else's: the run's files must be theirs
        os.chown(out, 1000, 1000)
    result = subprocess.run(
        ["bash", str(ROOT / "ops" / "compose-test.sh"), str(rec), str(out)],
        env={**os.environ, "WAVEGRASP_PACE": "lockstep",
             "WAVEGRASP_COMPOSE_PROJECT": f"wavegrasp-test-{os.getpid()}"},
        capture_output=True, text=True, timeout=1800)
    return rec, out, result


def test_compose_up_in_containers_grasps_and_records_every_frame(compose_run) -> None:
    rec, out, result = compose_run
    log = result.stdout[-4000:] + result.stderr[-4000:]
    assert result.returncode == 0, log

    # Every container ran and exited 0 (the script lists each one). The router made this
    # installation's logins first, and every service logged in with its own (the router
    # refuses a session without one: access control is on).
    exits = [line.split()[-1] for line in result.stderr.splitlines() if " exited " in line]
    assert len(exits) == 8 and set(exits) == {"0"}, log
    made = 3 * len(LOGINS) + 3  # each process's config, certificate and key; the CA's, logins
    assert f"made this installation's logins and certificates: {made} files in /keys" in (
        result.stdout + result.stderr), log

    # The recorder wrote the summary: the whole recording played, and the grasp succeeded.
    summary = json.loads((out / "summary.json").read_text())
    assert summary["ended"] == "finished" and summary["player"]["frames"] == 160, summary
    assert summary["outcomes"] and summary["outcomes"][0]["success"], summary["outcomes"]
    assert not summary["bad_messages"], summary["bad_messages"]

    # Every camera frame, bit-identical, as the launcher's run records them.
    payloads, _ = recorded(out / "run.mcap")
    assert payloads["/trisect/points"] == source_frames(rec)

    # The run's files belong to whoever owns the run folder (compose's caller, as a rule).
    owner = (out.stat().st_uid, out.stat().st_gid)
    assert {(p.stat().st_uid, p.stat().st_gid) for p in out.iterdir()} == {owner}


def test_the_image_holds_no_build_secret_and_runs_as_a_user(compose_run) -> None:
    """The CA bundle the build trusted is in no layer; no compiler is left."""
    assert compose_run[2].returncode == 0, compose_run[2].stderr[-3000:]
    docker = "/usr/bin/docker" if Path("/usr/bin/docker").exists() else "docker"
    probe = subprocess.run(
        [docker, "run", "--rm", "wavegrasp:latest", "sh", "-c",
         "id -un; ls /run/secrets 2>&1; env | grep -c PIP_CERT; "
         "command -v gcc cc g++ || echo no-compiler"],
        capture_output=True, text=True, timeout=120)
    assert probe.returncode == 0, probe.stderr
    lines = probe.stdout.split("\n")
    assert lines[0] == "wavegrasp"
    assert "No such file" in lines[1]
    assert lines[2] == "0"
    assert lines[3] == "no-compiler"
    history = subprocess.run([docker, "history", "--no-trunc", "wavegrasp:latest"],
                             capture_output=True, text=True, timeout=60).stdout
    assert "BEGIN CERTIFICATE" not in history

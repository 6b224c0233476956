"""One distribution, one import name: ``pip install .`` and ``pip install -e .`` both work."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import wavegrasp
import wavegrasp.schemas

from conftest import ROOT


def test_editable_install_maps_the_fixed_folders() -> None:
    assert Path(wavegrasp.__file__).parent == ROOT / "services"
    assert Path(wavegrasp.schemas.__file__).parent == ROOT / "schemas"


def test_non_editable_install_is_self_contained(tmp_path: Path) -> None:
    target = tmp_path / "site"
    try:
        subprocess.run([sys.executable, "-m", "pip", "install", "-q", "--no-deps", "--target",
                        str(target), str(ROOT)], check=True, timeout=300)
    finally:
        shutil.rmtree(ROOT / "build", ignore_errors=True)  # setuptools builds in the tree
    probe = ("import wavegrasp, wavegrasp.schemas, wavegrasp.ops.launcher, wavegrasp.player.main;"
             "from wavegrasp.schemas.export import schema_path;"
             "print(wavegrasp.__file__); print(schema_path('Clock').exists())")
    env = {**os.environ, "PYTHONPATH": str(target)}
    out = subprocess.run([sys.executable, "-I", "-c", probe.replace("import wavegrasp,", (
        f"import sys; sys.path.insert(0, {str(target)!r}); import wavegrasp,"))],
        capture_output=True, text=True, env=env, check=True, cwd=tmp_path).stdout.split()
    assert out[0].startswith(str(target)), out
    assert out[1] == "True", "exported JSON schemas are installed with the package"
    assert (target / "bin" / "wavegrasp").exists()

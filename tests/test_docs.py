"""The documentation: the site builds without a warning (broken links, pages outside the
navigation), and the README's links lead somewhere."""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

from conftest import ROOT


def test_the_site_builds_strictly(tmp_path: Path) -> None:
    result = subprocess.run([sys.executable, "-m", "mkdocs", "build", "--strict", "-d",
                             str(tmp_path / "site")], cwd=ROOT, capture_output=True, text=True,
                            timeout=300, env={**os.environ, "NO_MKDOCS_2_WARNING": "1"})
    assert result.returncode == 0, result.stderr[-3000:]
    assert (tmp_path / "site" / "vehicle" / "index.html").exists()


def test_the_readme_is_a_front_page_whose_links_lead_somewhere() -> None:
    text = (ROOT / "README.md").read_text()
    assert len(text.splitlines()) <= 150
    first = [line for line in text.splitlines()[:6] if line.startswith("bash ops/setup.sh")]
    assert first == ["bash ops/setup.sh && .venv/bin/wavegrasp up            # set up, then "
                     "replay the sample recording through the services",
                     "bash ops/setup.sh && .venv/bin/python -m pytest        # set up, then "
                     "run the tests"]
    for target in re.findall(r"\]\(([^)#\s]+)", text):
        if not target.startswith("http"):
            assert (ROOT / target).exists(), target


def test_the_pages_made_from_the_code_are_what_the_code_says() -> None:
    """docs/configuration.md and docs/message-types.md: every setting and message field."""
    result = subprocess.run([sys.executable, "-m", "wavegrasp.ops.docs", "--check"],
                            capture_output=True, text=True, timeout=120)
    assert result.returncode == 0, result.stderr
    text = (ROOT / "docs" / "configuration.md").read_text()
    assert "`WAVEGRASP_BUDGET_MBIT`" in text and "`WAVEGRASP_EPSILON_M`" in text

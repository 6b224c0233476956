"""Where the project and its default recording are.

``wavegrasp up`` with no recording replays ``recordings/sample.mcap`` when the checkout has
one; otherwise it generates the sample deterministically into a cache on first use
(``$WAVEGRASP_CACHE`` or ``~/.cache/wavegrasp``), with a progress bar.
"""

from __future__ import annotations

import os
import sys
from pathlib import Path

SAMPLE_SECONDS = 60.0
SAMPLE_SEED = 0


def project_root() -> Path:
    """The checkout this package runs from (editable install), else the current folder."""
    here = Path(__file__).resolve().parent.parent
    return here if (here / "docker-compose.yml").exists() else Path.cwd()


def cache_dir() -> Path:
    return Path(os.environ.get("WAVEGRASP_CACHE", Path.home() / ".cache" / "wavegrasp"))


def default_recording() -> Path:
    """The sample recording, generating it into the cache the first time."""
    shipped = project_root() / "recordings" / "sample.mcap"
    if shipped.exists():
        return shipped
    from wavegrasp.recording_io.synthetic import write_synthetic_recording

    path = cache_dir() / "recordings" / f"synthetic-{SAMPLE_SECONDS:.0f}s-seed{SAMPLE_SEED}.mcap"
    if not path.exists():
        print(f"generating the sample recording into {path} (first use only)", file=sys.stderr)
        path.parent.mkdir(parents=True, exist_ok=True)
        partial = path.with_suffix(".partial")
        write_synthetic_recording(partial, seconds=SAMPLE_SECONDS, seed=SAMPLE_SEED,
                                  progress=True)
        partial.replace(path)
    return path

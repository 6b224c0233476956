"""Where the project and its default recording are.

``wavegrasp up`` with no recording replays ``recordings/sample.mcap`` when the checkout has
one; otherwise it generates the sample deterministically into a cache on first use
(``$WAVEGRASP_CACHE`` or ``~/.cache/wavegrasp``), with a progress bar.
"""

from __future__ import annotations

import os
import sys
from pathlib import Path

# Wave 1 (the paper's largest) with the buoy, a minute: warm-up and several grasp attempts.
SAMPLE = {"wave": 1, "object": "buoy", "seconds": 60.0, "seed": 0}


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
    return cached_recording(**SAMPLE)


def cached_recording(wave: int, object: str, seconds: float, seed: int = 0,
                     irregular: bool = False) -> Path:
    """A wave-tank recording from the cache, generated (with a progress bar) on first use."""
    from wavegrasp.wavetank.record import GENERATOR_VERSION, RecordConfig, generate

    sea = "jonswap" if irregular else "regular"
    name = f"wave{wave}-{object}-{sea}-{seconds:g}s-seed{seed}-v{GENERATOR_VERSION}.mcap"
    path = cache_dir() / "recordings" / name
    if not path.exists():
        print(f"generating {path} (first use only)", file=sys.stderr)
        path.parent.mkdir(parents=True, exist_ok=True)
        partial = path.with_suffix(".partial")
        generate(RecordConfig(wave=wave, object=object, seconds=seconds, seed=seed,
                              irregular=irregular), partial, progress=True)
        partial.replace(path)
    return path

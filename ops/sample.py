"""Where the project and its default recording are.

``wavegrasp up`` with no recording replays ``recordings/sample.mcap`` when the checkout has
one; otherwise it generates the sample deterministically into a cache on first use
(``$WAVEGRASP_CACHE`` or ``~/.cache/wavegrasp``), with a progress bar.
"""

from __future__ import annotations

import hashlib
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


def recording_path(scenario: object = None, **config: object) -> Path:
    """Where :func:`cached_recording` keeps the recording of ``scenario`` or ``config``: the
    file name says the main ones and a hash of all of them."""
    from wavegrasp.wavetank.record import GENERATOR_VERSION, RecordConfig

    if scenario is not None:
        digest = hashlib.sha256(scenario.model_dump_json().encode()).hexdigest()[:8]
        stem = f"{scenario.name}-{scenario.seconds:g}s-seed{scenario.seed}"
    else:
        cfg = RecordConfig(**config)
        digest = hashlib.sha256(repr(cfg).encode()).hexdigest()[:8]
        stem = f"wave{cfg.wave}-{cfg.object}-{cfg.seconds:g}s-seed{cfg.seed}"
    return cache_dir() / "recordings" / f"{stem}-v{GENERATOR_VERSION}-{digest}.mcap"


def cached_recording(scenario: object = None, **config: object) -> Path:
    """A wave-tank recording from the cache, generated (with a progress bar) on first use.

    Either a :class:`~wavegrasp.wavetank.scenario.Scenario`, or ``config`` holding
    :class:`~wavegrasp.wavetank.record.RecordConfig`'s fields (wave, object, seconds, seed,
    ...): :func:`recording_path`.
    """
    from wavegrasp.wavetank.record import RecordConfig, generate

    what = scenario if scenario is not None else RecordConfig(**config)
    path = recording_path(scenario, **config)
    if not path.exists():
        print(f"generating {path} (first use only)", file=sys.stderr)
        path.parent.mkdir(parents=True, exist_ok=True)
        partial = path.with_suffix(f".{os.getpid()}.partial")
        generate(what, partial, progress=sys.stderr.isatty())
        partial.replace(path)
    return path

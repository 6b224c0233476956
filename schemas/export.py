"""Export every message's JSON Schema next to the models, in ``schemas/json/NAME.schema.json``.

Run ``python -m wavegrasp.schemas.export`` after changing a model; a test fails while the files
on disk differ from the models.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

from wavegrasp.schemas import MESSAGE_TYPES

JSON_DIR = Path(__file__).with_name("json")


def schema_text(name: str) -> str:
    """The JSON Schema of message ``name`` as the exact text that is stored on disk."""
    return json.dumps(MESSAGE_TYPES[name].model_json_schema(), indent=2, sort_keys=True) + "\n"


def schema_path(name: str) -> Path:
    return JSON_DIR / f"{name}.schema.json"


def main(argv: list[str] | None = None) -> int:
    JSON_DIR.mkdir(exist_ok=True)
    for name in MESSAGE_TYPES:
        schema_path(name).write_text(schema_text(name))
    stale = {p.name for p in JSON_DIR.glob("*.schema.json")} - {
        schema_path(n).name for n in MESSAGE_TYPES
    }
    for name in stale:
        (JSON_DIR / name).unlink()
    print(f"wrote {len(MESSAGE_TYPES)} schemas to {JSON_DIR}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())

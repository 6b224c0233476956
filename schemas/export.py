"""Export every message's JSON Schema and ROS 2 interface next to the models:
``schemas/json/NAME.schema.json`` and ``schemas/msg/NAME.msg`` (the ``wavegrasp_msgs`` package,
``schemas/package.xml``, that colcon builds).

Run ``python -m wavegrasp.schemas.export`` after changing a model; a test fails while the files
on disk differ from the models.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

from wavegrasp.schemas import MESSAGE_TYPES
from wavegrasp.schemas.ros import definitions

JSON_DIR = Path(__file__).with_name("json")
MSG_DIR = Path(__file__).with_name("msg")


def schema_text(name: str) -> str:
    """The JSON Schema of message ``name`` as the exact text that is stored on disk."""
    return json.dumps(MESSAGE_TYPES[name].model_json_schema(), indent=2, sort_keys=True) + "\n"


def schema_path(name: str) -> Path:
    return JSON_DIR / f"{name}.schema.json"


def _write_all(folder: Path, texts: dict[str, str], suffix: str) -> None:
    """Write ``texts`` (file name without ``suffix`` -> text) into ``folder``, removing files
    of that suffix no longer among them."""
    folder.mkdir(exist_ok=True)
    for name, text in texts.items():
        (folder / f"{name}{suffix}").write_text(text)
    for path in folder.glob(f"*{suffix}"):
        if path.name.removesuffix(suffix) not in texts:
            path.unlink()


def main(argv: list[str] | None = None) -> int:
    _write_all(JSON_DIR, {n: schema_text(n) for n in MESSAGE_TYPES}, ".schema.json")
    _write_all(MSG_DIR, definitions(), ".msg")
    print(f"wrote {len(MESSAGE_TYPES)} schemas to {JSON_DIR} and {len(definitions())} "
          f"interfaces to {MSG_DIR}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())

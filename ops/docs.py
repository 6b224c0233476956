"""``python -m wavegrasp.ops.docs [--check]``: the documentation pages made from the code.

``docs/configuration.md`` from the services' settings models (each setting, its
environment variable, default and description) and ``docs/message-types.md`` from the
message models (each type's key, ROS 2 type and fields). ``--check`` writes nothing and
exits 1 if a page is not what the code says (a test runs it).
"""

from __future__ import annotations

import argparse
import importlib
import sys
import typing

from pydantic import BaseModel

from wavegrasp.ops.sample import project_root
from wavegrasp.runtime.settings import Settings
from wavegrasp.schemas import MESSAGE_TYPES
from wavegrasp.schemas.ros import msgtype as ros_msgtype

#: Each service's settings model, in the pipeline's order.
SETTINGS = {
    "player": "wavegrasp.player.main:PlayerSettings",
    "edge": "wavegrasp.edge.main:EdgeSettings",
    "perception": "wavegrasp.perception.main:PerceptionSettings",
    "predictor": "wavegrasp.predictor.main:PredictorSettings",
    "planner": "wavegrasp.planner.main:PlannerSettings",
    "gate": "wavegrasp.gate.main:GateSettings",
    "sim": "wavegrasp.sim.main:SimSettings",
    "recorder": "wavegrasp.recorder.main:RecorderSettings",
    "scene": "wavegrasp.scene.main:SceneSettings",
    "foxglove": "wavegrasp.foxglove.main:FoxgloveSettings",
}


def type_name(annotation: object) -> str:
    text = str(annotation) if typing.get_origin(annotation) else getattr(
        annotation, "__name__", str(annotation))
    return (text.replace("typing.", "").replace("pathlib.", "").replace("|", "or")
            .replace("wavegrasp.schemas.messages.", ""))


def cell(text: object) -> str:
    return str(text).replace("|", "\\|").replace("\n", " ")


def env_var(name: str) -> str:
    return name.upper() if name.startswith("zenoh_") else f"WAVEGRASP_{name.upper()}"


def field_rows(model: type[BaseModel], skip: set[str]) -> list[str]:
    rows = []
    for name, f in model.model_fields.items():
        if name in skip or name == "service":
            continue
        default = "(required)" if f.is_required() else (
            f.default_factory() if f.default_factory else f.default)  # type: ignore[call-arg]
        rows.append(f"| `{env_var(name)}` | {cell(type_name(f.annotation))} | "
                    f"`{cell(default)}` | {cell(f.description or '')} |")
    return rows


def configuration() -> str:
    header = ["| variable | type | default | what |", "|---|---|---|---|"]
    lines = ["# Configuration", "",
             "Every setting comes from the environment (`docker-compose.yml` sets them per "
             "service; `wavegrasp up` passes its own environment's `WAVEGRASP_` and `ZENOH_` "
             "variables on); a command-line option wins. Made from the settings models by "
             "`python -m wavegrasp.ops.docs`.", "", "## Every service", "", *header,
             *field_rows(Settings, set())]
    common = set(Settings.model_fields)
    for service, where in SETTINGS.items():
        module, _, name = where.partition(":")
        model = getattr(importlib.import_module(module), name)
        lines += ["", f"## {service}", "", f"`wavegrasp {service}` ({name}).", "", *header,
                  *field_rows(model, common)]
    return "\n".join(lines) + "\n"


def message_types() -> str:
    lines = ["# Message types", "",
             "Our messages, each a ROS 2 type of package `wavegrasp_msgs` (`schemas/msg/`) "
             "carried as CDR (see [Messages and contracts](messages.md)). Made from the "
             "models by `python -m wavegrasp.ops.docs`."]
    for name, model in sorted(MESSAGE_TYPES.items()):
        doc = " ".join((model.__doc__ or "").split())
        lines += ["", f"## {name}", "", f"`{ros_msgtype(name)}`. {doc}", "",
                  "| field | type | what |", "|---|---|---|"]
        lines += [f"| `{f}` | {cell(type_name(info.annotation))} | {cell(info.description or '')} |"
                  for f, info in model.model_fields.items()]
    return "\n".join(lines) + "\n"


PAGES = {"configuration.md": configuration, "message-types.md": message_types}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m wavegrasp.ops.docs", description=__doc__)
    parser.add_argument("--check", action="store_true", help="exit 1 if a page is stale")
    args = parser.parse_args(argv)
    stale = []
    for name, make in PAGES.items():
        path = project_root() / "docs" / name
        text = make()
        if args.check:
            if not path.exists() or path.read_text() != text:
                stale.append(str(path))
        else:
            path.write_text(text)
    if stale:
        print(f"stale: {', '.join(stale)}: run python -m wavegrasp.ops.docs", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

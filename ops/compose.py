"""Read docker-compose.yml the way ``docker compose`` would, for the local launcher.

Only what the launcher needs: each service's command, environment, depends_on (with its
condition) and labels, with ``${VAR}``, ``${VAR:-default}`` and ``${VAR-default}`` interpolated.
"""

from __future__ import annotations

import re
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml

_VAR = re.compile(r"\$\{([A-Za-z_][A-Za-z0-9_]*)(?:(:?-)([^}]*))?\}|\$\$")


@dataclass
class ComposeService:
    name: str
    command: list[str]
    environment: dict[str, str] = field(default_factory=dict)
    depends_on: dict[str, str] = field(default_factory=dict)  # name -> condition
    labels: dict[str, str] = field(default_factory=dict)
    restart: str = "no"
    profiles: list[str] = field(default_factory=list)

    def restarts_after(self, exit_code: int, restarts_so_far: int) -> bool:
        """Whether compose's ``restart`` policy starts the service again after it exited with
        ``exit_code``, having been restarted ``restarts_so_far`` times already."""
        policy, _, limit = self.restart.partition(":")
        if policy in ("always", "unless-stopped"):
            return True
        if policy != "on-failure" or exit_code == 0:
            return False
        return not limit or restarts_so_far < int(limit)


RESTART_POLICY = re.compile(r"no|always|unless-stopped|on-failure(:[0-9]+)?")


def interpolate(text: str, variables: Mapping[str, str]) -> str:
    """Compose variable substitution on one string."""

    def sub(m: re.Match[str]) -> str:
        if m.group(0) == "$$":
            return "$"
        name, op, default = m.group(1), m.group(2), m.group(3) or ""
        value = variables.get(name)
        if op == ":-" and not value:
            return default
        if op == "-" and value is None:
            return default
        return value or ""

    return _VAR.sub(sub, text)


def _as_dict(value: Any, what: str) -> dict[str, str]:
    if value is None:
        return {}
    if isinstance(value, list):  # ["A=1", "B"] form
        return dict(item.split("=", 1) if "=" in item else (item, "") for item in value)
    if isinstance(value, dict):
        return {str(k): "" if v is None else str(v) for k, v in value.items()}
    raise ValueError(f"{what}: expected a mapping or a list")


def load_compose(path: Path, variables: Mapping[str, str],
                 profiles: frozenset[str] = frozenset()) -> dict[str, ComposeService]:
    """Parse ``path``; raises ValueError naming the file and the service that is malformed.

    As compose does, a service with ``profiles`` is left out unless one of them is in
    ``profiles``.
    """
    try:
        doc = yaml.safe_load(path.read_text())
    except (OSError, yaml.YAMLError) as exc:
        raise ValueError(f"{path}: cannot read compose file: {exc}") from None
    if not isinstance(doc, dict) or not isinstance(doc.get("services"), dict):
        raise ValueError(f"{path}: no 'services' mapping")
    services: dict[str, ComposeService] = {}
    for name, spec in doc["services"].items():
        where = f"{path}: service {name}"
        wanted = spec.get("profiles") or []
        if wanted and not set(wanted) & profiles:
            continue
        command = spec.get("command")
        if isinstance(command, str):
            command = command.split()
        if not command:
            raise ValueError(f"{where}: needs a command")
        restart = str(spec.get("restart", "no"))
        if not RESTART_POLICY.fullmatch(restart):
            raise ValueError(f"{where}: restart must be no, always, unless-stopped or "
                             f"on-failure[:N], got {restart!r}")
        deps = spec.get("depends_on") or {}
        if isinstance(deps, list):
            deps = {d: {"condition": "service_started"} for d in deps}
        services[name] = ComposeService(
            name=name,
            command=[interpolate(str(c), variables) for c in command],
            environment={k: interpolate(v, variables)
                         for k, v in _as_dict(spec.get("environment"), where).items()},
            depends_on={d: (c or {}).get("condition", "service_started") for d, c in deps.items()},
            labels=_as_dict(spec.get("labels"), where),
            restart=restart,
            profiles=list(wanted),
        )
    for svc in services.values():
        for dep in svc.depends_on:
            if dep not in services:
                raise ValueError(f"{path}: service {svc.name} depends on unknown service {dep}")
    return services


def start_order(services: Mapping[str, ComposeService]) -> list[str]:
    """Services ordered so each comes after what it depends on; raises ValueError on a cycle."""
    order: list[str] = []
    state: dict[str, int] = {}

    def visit(name: str) -> None:
        if state.get(name) == 2:
            return
        if state.get(name) == 1:
            raise ValueError(f"depends_on cycle through service {name}")
        state[name] = 1
        for dep in services[name].depends_on:
            visit(dep)
        state[name] = 2
        order.append(name)

    for name in services:
        visit(name)
    return order

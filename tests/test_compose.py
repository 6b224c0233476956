"""docker-compose.yml: valid per the Compose Specification, and what the launcher reads of it."""

from __future__ import annotations

import json
from pathlib import Path

import jsonschema
import pytest
import yaml

from wavegrasp.ops.compose import interpolate, load_compose, start_order

from conftest import ROOT

SPEC = ROOT.parent / "shared" / "compose-spec" / "compose-spec.json"
COMPOSE = ROOT / "docker-compose.yml"
TWO_HOSTS = ROOT / "docker-compose.two-hosts.yml"


def test_compose_file_follows_the_compose_specification() -> None:
    if not SPEC.exists():
        pytest.skip(f"{SPEC} not beside the checkout")
    validator = jsonschema.Draft7Validator(json.loads(SPEC.read_text()))
    validator.validate(yaml.safe_load(COMPOSE.read_text()))
    validator.validate(yaml.safe_load((ROOT / "ops" / "compose-rt-cgroup-v1.yml").read_text()))
    validator.validate(yaml.safe_load(TWO_HOSTS.read_text()))


def test_the_two_host_file_splits_the_services_as_the_tether_run_does() -> None:
    """Each host's profile runs its side (as ``wavegrasp up --tether`` places them), every
    service logs in, the vehicle's router holds the camera's clouds off the tether and the
    topside's links to it over TLS; the topside reads the edge stage's clouds."""
    from wavegrasp.ops.tether import VEHICLE

    env = {"WAVEGRASP_TETHER_INTERFACE": "eth1", "WAVEGRASP_VEHICLE_HOST": "10.0.0.2"}
    vehicle = load_compose(TWO_HOSTS, env, frozenset({"vehicle"}))
    topside = load_compose(TWO_HOSTS, env, frozenset({"topside"}))
    assert set(vehicle) == {"router-vehicle", *VEHICLE}
    assert set(topside) == {"router-topside", "perception", "predictor", "planner", "gate",
                            "recorder"}
    router = vehicle["router-vehicle"].environment
    assert router["WAVEGRASP_HOLD_KEYS"] == "trisect/points"
    assert router["WAVEGRASP_HOLD_INTERFACES"] == "eth1"
    assert "tls/0.0.0.0:7448" in router["ZENOH_LISTEN"]
    assert topside["router-topside"].environment["WAVEGRASP_ROUTER_CONNECT"] == "tls/10.0.0.2:7448"
    for services in (vehicle, topside):
        for name, svc in services.items():
            assert svc.environment["ZENOH_CONFIG"].startswith("/keys/"), name
            if not name.startswith("router"):
                assert svc.environment["WAVEGRASP_POINTS_KEY"] == "wavegrasp/edge/points"


def test_every_service_runs_a_wavegrasp_command_from_one_image() -> None:
    doc = yaml.safe_load(COMPOSE.read_text())
    for name, spec in doc["services"].items():
        assert spec["image"] == "wavegrasp:latest", name
        assert spec["build"]["dockerfile"] == "ops/Dockerfile", name
        assert spec["command"][:2] == ["wavegrasp", name], name
    assert (ROOT / "ops" / "Dockerfile").exists()


def test_launcher_reads_services_in_dependency_order() -> None:
    services = load_compose(COMPOSE, {"WAVEGRASP_ROUTER_HOST": "127.0.0.1",
                                      "WAVEGRASP_ROUTER_PORT": "9999",
                                      "WAVEGRASP_RECORDING": "/data/x.mcap"})
    order = start_order(services)
    assert order[0] == "router" and order[-1] == "player"
    assert services["recorder"].environment["ZENOH_CONNECT"] == "tcp/127.0.0.1:9999"
    assert services["player"].environment["WAVEGRASP_RECORDING"] == "/data/x.mcap"
    assert services["player"].command[3] == "realtime"  # the default applies when unset
    assert services["player"].labels["wavegrasp.ends-run"] == "true"
    assert services["player"].depends_on == {
        name: "service_healthy"
        for name in ("recorder", "perception", "predictor", "planner", "gate", "sim")}


def test_interpolation_follows_compose_rules() -> None:
    v = {"SET": "a", "EMPTY": ""}
    assert interpolate("${SET:-x}/${EMPTY:-y}/${UNSET:-z}", v) == "a/y/z"
    assert interpolate("${EMPTY-x}/${UNSET-z}/$${SET}", v) == "/z/${SET}"


def test_dependency_cycle_and_unknown_service_are_named(tmp_path: Path) -> None:
    bad = tmp_path / "compose.yml"
    bad.write_text("services:\n  a: {command: [x], depends_on: [b]}\n"
                   "  b: {command: [x], depends_on: [a]}\n")
    with pytest.raises(ValueError, match="cycle"):
        start_order(load_compose(bad, {}))
    bad.write_text("services:\n  a: {command: [x], depends_on: [ghost]}\n")
    with pytest.raises(ValueError, match="ghost"):
        load_compose(bad, {})

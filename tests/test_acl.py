"""Access control on the router (ops/zenoh/acl/): only the gate's login gets a decision through,
only the arm's login an arm state, and every service keeps its own keys and liveliness."""

from __future__ import annotations

import queue
import socket
import time
from collections.abc import Iterator
from pathlib import Path

import pytest
import zenoh

from wavegrasp.gate.main import DECISION_KEY
from wavegrasp.ops.launcher import free_port
from wavegrasp.perception.main import OBJECT_KEY
from wavegrasp.planner.main import PLAN_KEY
from wavegrasp.runtime.bus import Bus, config_file, open_session, zenoh_config
from wavegrasp.runtime.settings import ArmTopics, Settings
from wavegrasp.schemas import Header, ObjectObservation, Vec3
from wavegrasp.sim.main import ARM_STATE_KEY

from conftest import ROOT, spawn, stop, wait_until, wavegrasp_cmd

ACL = ROOT / "ops" / "zenoh" / "acl"
ARM = ArmTopics()  # the arm's ros2_control topics: only the gate commands, only the arm reports
COMMANDS = [ARM.arm_trajectory_key, ARM.jaw_trajectory_key]
#: Keys each test login may publish on (the sim logs in as the arm).
OWN_KEYS = {"gate": [DECISION_KEY, *COMMANDS], "sim": [ARM_STATE_KEY, ARM.joint_states_key],
            "planner": [PLAN_KEY]}
#: What each may not publish: the others' reserved keys and wildcards that would reach them.
FORGERIES = {
    "gate": [ARM_STATE_KEY, "wavegrasp/sim/*", "wavegrasp/**", ARM.joint_states_key, "**"],
    "sim": [DECISION_KEY, "wavegrasp/gate/*", "wavegrasp/**", *COMMANDS, "arm/**"],
    "planner": [DECISION_KEY, ARM_STATE_KEY, "wavegrasp/gate/*", "wavegrasp/sim/*",
                "wavegrasp/**", *COMMANDS, ARM.joint_states_key, "jaw/**"],
}


@pytest.fixture(scope="module")
def endpoint() -> Iterator[str]:
    """A ``wavegrasp router`` with ops/zenoh/acl/router.json5, run from the repository root
    (the file names its credentials relative to it)."""
    port = free_port()
    proc = spawn(wavegrasp_cmd("router", "--listen", f"tcp/127.0.0.1:{port}",
                               "--config", str(ACL / "router.json5")), {}, cwd=ROOT)
    deadline = time.monotonic() + 15
    while proc.poll() is None and time.monotonic() < deadline:
        with socket.socket() as s:
            if s.connect_ex(("127.0.0.1", port)) == 0:
                break
        time.sleep(0.05)
    assert proc.poll() is None, "the router refused its access-control config"
    yield f"tcp/127.0.0.1:{port}"
    stop(proc)


def settings(service: str, endpoint: str, **kw) -> Settings:
    """A service's settings with access control on: ZENOH_CONFIG names its login file."""
    return Settings.from_env(service, env={"ZENOH_CONNECT": endpoint,
                                           "ZENOH_CONFIG": str(ACL / "{service}.json5")}, **kw)


class Watcher:
    """Every sample under wavegrasp/ that reaches a session, as ``(key, payload)``; a raw
    subscriber, not the bus's, so it also sees samples put on wildcard keys."""

    def __init__(self, session: zenoh.Session) -> None:
        self.samples: list[tuple[str, bytes]] = []
        self.sub = session.declare_subscriber(
            "**", lambda s: self.samples.append((str(s.key_expr), s.payload.to_bytes())))

    def payloads(self) -> list[bytes]:
        return [payload for _, payload in list(self.samples)]


def delivered(sender: Bus, key: str, watcher: Watcher, timeout: float = 5.0) -> bool:
    """Publish a fresh marker on ``key`` every 0.1 s until ``watcher`` gets it."""
    marker = f"{sender.service} {key} {time.monotonic_ns()}".encode()

    def seen() -> bool:
        if marker in watcher.payloads():
            return True
        sender.publish_bytes(key, marker)
        return False

    return wait_until(seen, timeout=timeout, period=0.1)


def test_only_the_gate_decides_and_commands_and_only_the_arm_reports_its_state(
        endpoint: str) -> None:
    buses = {name: Bus(settings(name, endpoint)) for name in ["recorder", *OWN_KEYS]}
    try:
        watcher = Watcher(buses["recorder"].session)  # another process's view, via the router
        for name, keys in OWN_KEYS.items():
            for key in keys:
                assert delivered(buses[name], key, watcher), f"{name} cannot publish {key}"
        for name, keys in FORGERIES.items():
            for key in keys:
                buses[name].publish_bytes(key, f"forged by {name} on {key}".encode())
            # Samples from one session keep their order through the router: a forgery let
            # through would arrive before this marker.
            assert delivered(buses[name], OWN_KEYS[name][0], watcher, timeout=2.0)
        forged = [(k, p) for k, p in list(watcher.samples) if p.startswith(b"forged")]
        assert forged == []
    finally:
        for bus in buses.values():
            bus.close()


def test_services_keep_their_own_keys_and_liveliness(endpoint: str) -> None:
    perception, planner = (Bus(settings(name, endpoint)) for name in ("perception", "planner"))
    try:
        got: queue.SimpleQueue[ObjectObservation] = queue.SimpleQueue()
        planner.subscribe(OBJECT_KEY, lambda m, d: got.put(m), ObjectObservation)
        perception.declare_alive()
        sent = ObjectObservation(header=Header(seq=3, stamp_ns=5), centroid=Vec3(x=0.1, y=0, z=1),
                                 points_used=10)

        def arrived() -> bool:
            perception.publish(OBJECT_KEY, sent)
            while not planner.inbox.empty():
                planner.dispatch(planner.inbox.get())
            return not got.empty()

        assert wait_until(arrived, timeout=5, period=0.1)
        assert got.get().centroid == sent.centroid
        assert not planner.wait_for_services(["perception", "router"], timeout_s=5)
    finally:
        perception.close()
        planner.close()


def test_no_session_without_the_right_password(endpoint: str, tmp_path: Path) -> None:
    open_session(settings("gate", endpoint)).close()  # the router is up and the login works
    logins = {"gate": "guess", "intruder": "example-only-gate-password-replace-me"}
    for user, password in logins.items():
        (tmp_path / f"{user}.json5").write_text(
            f'{{transport: {{auth: {{usrpwd: {{user: "{user}", password: "{password}"}}}}}}}}')
    for conf in (str(tmp_path / "gate.json5"), str(tmp_path / "intruder.json5"), None):
        s = Settings(service="gate", zenoh_connect=[endpoint], zenoh_config=conf,
                     connect_timeout_s=0.3)
        with pytest.raises(ConnectionError, match=f"cannot open zenoh session on {endpoint}"):
            open_session(s).close()


def test_a_bad_config_file_is_named(tmp_path: Path) -> None:
    s = Settings(service="sim", zenoh_config=str(tmp_path / "{service}.json5"))
    assert config_file(s) == str(tmp_path / "sim.json5")
    with pytest.raises(ValueError, match=f"sim: {tmp_path / 'sim.json5'}: not a usable"):
        zenoh_config(s)
    (tmp_path / "sim.json5").write_text("{transport: {auth: {usrpwd: {username: 1}}}}")
    with pytest.raises(ValueError, match="sim.json5: not a usable zenoh config.*username"):
        zenoh_config(s)
    (tmp_path / "sim.json5").write_text('{mode: "router", listen: {endpoints: ["tcp/x:1"]}}')
    conf = zenoh_config(s)  # ours on top of the file's
    assert conf.get_json("mode") == '"client"' and conf.get_json("listen/endpoints") == "[]"


def test_a_router_does_not_wait_for_scouting_unless_its_file_says_so(tmp_path: Path) -> None:
    router = Settings(service="router", zenoh_mode="router", zenoh_listen=["tcp/127.0.0.1:0"])
    assert zenoh_config(router).get_json("scouting/delay") == "0"
    (tmp_path / "router.json5").write_text("{scouting: {delay: 300}}")
    router.zenoh_config = str(tmp_path / "router.json5")
    assert zenoh_config(router).get_json("scouting/delay") == "300"


def test_the_tls_example_keeps_the_rules_of_the_acl() -> None:
    """ops/zenoh/router-tls.json5.example parses and differs from the ACL only in subjects
    (its certificate paths are placeholders, so it is not opened)."""
    example = zenoh.Config.from_json5((ACL.parent / "router-tls.json5.example").read_text())
    acl = zenoh.Config.from_file(str(ACL / "router.json5"))
    for key in ("access_control/rules", "access_control/policies", "transport/auth"):
        assert example.get_json(key) == acl.get_json(key), key
    assert '"enable_mtls":true' in example.get_json("transport/link/tls")

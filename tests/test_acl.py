"""Access control on the router (ops/zenoh/acl/router.json5, with this installation's logins
and certificates from ``wavegrasp keys``): only the gate's login gets a decision through, only
the arm's login an arm state, every service keeps its own keys and liveliness, and a TLS link
needs a certificate of this installation's own."""

from __future__ import annotations

import json
import queue
import re
import socket
import subprocess
import time
from collections.abc import Iterator
from pathlib import Path

import pytest
import zenoh

from wavegrasp.gate.main import DECISION_KEY
from wavegrasp.ops.keys import LOGINS, make_keys
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
def keys(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """This installation's logins and certificates (``wavegrasp keys``)."""
    out = tmp_path_factory.mktemp("keys")
    make_keys(out, [])
    return out


@pytest.fixture(scope="module")
def endpoints(keys: Path) -> Iterator[tuple[str, str]]:
    """A ``wavegrasp router`` with the config ``wavegrasp keys`` made: its TCP endpoint on the
    loopback and its TLS one (mutual)."""
    port, tls_port = free_port(), free_port()
    proc = spawn(wavegrasp_cmd("router", "--listen", f"tcp/127.0.0.1:{port},"
                               f"tls/127.0.0.1:{tls_port}", "--config", str(keys / "router.json5")),
                 {})
    deadline = time.monotonic() + 15
    while proc.poll() is None and time.monotonic() < deadline:
        with socket.socket() as s:
            if s.connect_ex(("127.0.0.1", port)) == 0:
                break
        time.sleep(0.05)
    assert proc.poll() is None, "the router refused its access-control config"
    yield f"tcp/127.0.0.1:{port}", f"tls/127.0.0.1:{tls_port}"
    stop(proc)


@pytest.fixture(scope="module")
def endpoint(endpoints: tuple[str, str]) -> str:
    return endpoints[0]


def settings(service: str, endpoint: str, keys: Path, **kw) -> Settings:
    """A service's settings with access control on: ZENOH_CONFIG names its login file."""
    return Settings.from_env(service, env={"ZENOH_CONNECT": endpoint,
                                           "ZENOH_CONFIG": str(keys / "{service}.json5")}, **kw)


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
        endpoint: str, keys: Path) -> None:
    buses = {name: Bus(settings(name, endpoint, keys)) for name in ["recorder", *OWN_KEYS]}
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


def test_services_keep_their_own_keys_and_liveliness(endpoint: str, keys: Path) -> None:
    perception, planner = (Bus(settings(name, endpoint, keys))
                           for name in ("perception", "planner"))
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


def test_no_session_without_the_right_password(endpoint: str, keys: Path,
                                               tmp_path: Path) -> None:
    open_session(settings("gate", endpoint, keys)).close()  # the router is up, the login works
    other = tmp_path / "other"  # another installation's: the same logins, other passwords
    make_keys(other, [])
    logins = {"gate": "guess", "intruder": "anything"}
    for user, password in logins.items():
        (tmp_path / f"{user}.json5").write_text(
            f'{{transport: {{auth: {{usrpwd: {{user: "{user}", password: "{password}"}}}}}}}}')
    for conf in (tmp_path / "gate.json5", tmp_path / "intruder.json5", other / "gate.json5",
                 None):
        s = Settings(service="gate", zenoh_connect=[endpoint], zenoh_config=conf and str(conf),
                     connect_timeout_s=0.3)
        with pytest.raises(ConnectionError, match=f"cannot open zenoh session on {endpoint}"):
            open_session(s).close()


def test_a_tls_link_needs_this_installations_certificate(endpoints: tuple[str, str],
                                                         keys: Path, tmp_path: Path) -> None:
    """Mutual TLS: the router shows a certificate of this installation's CA and asks each
    client for one; the login is checked as well."""
    _tcp, tls = endpoints
    open_session(settings("sim", tls, keys)).close()  # the arm's certificate and login
    login_only = tmp_path / "login-only.json5"  # the right login, no certificate
    login = json.loads((keys / "sim.json5").read_text().split("\n", 1)[1])
    del login["transport"]["link"]
    login_only.write_text(json.dumps(login))
    other = tmp_path / "other"
    make_keys(other, [])
    stranger = json.loads((other / "sim.json5").read_text().split("\n", 1)[1])
    stranger["transport"]["auth"] = login["transport"]["auth"]  # the right login, their CA
    (tmp_path / "stranger.json5").write_text(json.dumps(stranger))
    for conf in (login_only, tmp_path / "stranger.json5"):
        s = Settings(service="sim", zenoh_connect=[tls], zenoh_config=str(conf),
                     connect_timeout_s=0.5)
        with pytest.raises(ConnectionError, match=f"cannot open zenoh session on {tls}"):
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


def test_keys_are_made_per_installation_and_none_is_committed(keys: Path,
                                                              tmp_path: Path) -> None:
    """``wavegrasp keys`` keeps the rules of ops/zenoh/acl/router.json5, gives every login a
    password of its own, readable by its owner and group only, and a second installation other
    ones;
    the repository holds no password."""
    made = zenoh.Config.from_file(str(keys / "router.json5"))
    rules = zenoh.Config.from_file(str(ACL / "router.json5"))
    for key in ("access_control/rules", "access_control/policies", "access_control/subjects"):
        assert made.get_json(key) == rules.get_json(key), key
    assert json.loads(made.get_json("transport/auth/usrpwd/dictionary_file")) == str(
        keys / "credentials.txt")
    assert json.loads(made.get_json("transport/link/tls/enable_mtls")) is True
    lines = (keys / "credentials.txt").read_text().splitlines()
    passwords = dict(line.split(":", 1) for line in lines)
    assert set(passwords) == {"recorder", "perception", "predictor", "planner", "gate", "arm",
                              "player", "edge", "foxglove", "scene", "launcher",
                              "health-check", "router"}
    assert len(set(passwords.values())) == len(passwords)
    assert all(len(p) >= 32 for p in passwords.values())
    assert {oct(p.stat().st_mode & 0o777) for p in keys.iterdir()} == {"0o640"}
    assert oct(keys.stat().st_mode & 0o777) == "0o750"
    again = subprocess.run(wavegrasp_cmd("keys", "--out", str(keys)), capture_output=True,
                           text=True)
    assert again.returncode == 0 and "holds keys already: kept" in again.stderr
    assert (keys / "credentials.txt").read_text().splitlines() == lines
    make_keys(tmp_path, [])
    assert not set(lines) & set((tmp_path / "credentials.txt").read_text().splitlines())
    tracked = subprocess.run(["git", "ls-files"], cwd=ROOT, capture_output=True,
                             text=True).stdout.split()
    assert not [f for f in tracked if f.endswith("credentials.txt") or f.endswith(".pem")]
    assert not [f for f in tracked if f.endswith(".json5")
                and re.search(r'password"?\s*:\s*"', (ROOT / f).read_text())]


def test_a_router_with_keys_makes_them_first_and_runs_on_them(tmp_path: Path) -> None:
    """``wavegrasp router --keys DIR`` (compose's router: WAVEGRASP_KEYS) makes this
    installation's logins where there are none, then requires them."""
    keys, port = tmp_path / "keys", free_port()
    proc = spawn(wavegrasp_cmd("router", "--listen", f"tcp/127.0.0.1:{port}", "--keys",
                               str(keys), "--config", str(keys / "router.json5")), {})
    try:
        endpoint = f"tcp/127.0.0.1:{port}"
        assert wait_until(lambda: (keys / "gate.json5").exists(), timeout=15, period=0.1)
        s = settings("gate", endpoint, keys, connect_timeout_s=15)
        open_session(s).close()
        # Every login of LOGINS, and the router's own for its links to other routers.
        assert len((keys / "credentials.txt").read_text().splitlines()) == len(
            [login for login in LOGINS.values() if login]) + 1
        with pytest.raises(ConnectionError, match="cannot open zenoh session"):
            open_session(Settings(service="gate", zenoh_connect=[endpoint],
                                  connect_timeout_s=0.3)).close()
    finally:
        stop(proc)


def test_across_a_tether_only_the_gate_commands_the_arm_and_only_the_arm_reports(
        keys: Path) -> None:
    """Two routers, the vehicle's and the topside's, each with this installation's config:
    the topside's links to the vehicle's over mutual TLS with its own login and passes on
    what its own rules let in. The gate's commands reach the arm's side, the arm's state the
    topside; a command forged topside, or a decision forged on the vehicle, goes nowhere."""
    port, tls_port, top_port = free_port(), free_port(), free_port()
    routers = [spawn(wavegrasp_cmd("router", "--listen", f"tcp/127.0.0.1:{port},"
                                   f"tls/127.0.0.1:{tls_port}", "--config",
                                   str(keys / "router.json5")), {})]
    routers.append(spawn(wavegrasp_cmd("router", "--listen", f"tcp/127.0.0.1:{top_port}",
                                       "--config", str(keys / "router.json5")),
                         {"WAVEGRASP_ROUTER_CONNECT": f"tls/localhost:{tls_port}"}))
    vehicle, topside = f"tcp/127.0.0.1:{port}", f"tcp/127.0.0.1:{top_port}"
    buses: list[Bus] = []
    try:
        def bus(name: str, endpoint: str) -> Bus:
            buses.append(Bus(settings(name, endpoint, keys, connect_timeout_s=15)))
            return buses[-1]

        gate, planner, recorder = (bus(n, topside) for n in ("gate", "planner", "recorder"))
        sim, player = bus("sim", vehicle), bus("player", vehicle)
        on_vehicle, on_topside = Watcher(sim.session), Watcher(recorder.session)
        assert delivered(gate, ARM.arm_trajectory_key, on_vehicle, timeout=15)
        assert delivered(sim, ARM.joint_states_key, on_topside)
        planner.publish_bytes(ARM.arm_trajectory_key, b"forged by planner")
        player.publish_bytes(DECISION_KEY, b"forged by player")
        assert delivered(planner, PLAN_KEY, on_vehicle)  # after the forgery, in order
        assert delivered(player, "trisect/points", on_topside)
        forged = [p for w in (on_vehicle, on_topside) for p in w.payloads()
                  if p.startswith(b"forged")]
        assert forged == []
    finally:
        for b in buses:
            b.close()
        for proc in routers:
            stop(proc)

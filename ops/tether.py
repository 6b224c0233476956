"""An ROV's tether on one machine: the vehicle's network namespace, joined to this one by a veth
pair shaped to the tether's bandwidth.

``wavegrasp up RECORDING --tether MBIT`` runs the vehicle's services (the player, the camera's
stand-in, and the sim, the arm's) and a router of their own in the namespace; the topside's
(perception, predictor, planner, gate, recorder) and their router stay here, and the topside
router connects to the vehicle's across the pair. Each end of the pair sends at most MBIT
Mbit/s (``tc``'s token bucket filter, as a tether's modems would), so what crosses is what a
tether would carry; its bytes are counted on the topside end. Needs root (``ip netns``).
"""

from __future__ import annotations

import os
import subprocess
import threading
import time
from dataclasses import dataclass, field, replace
from pathlib import Path

from wavegrasp.ops.compose import ComposeService
from wavegrasp.ops.status import CAMERA_KEY

#: The services that run on the vehicle: the camera (its stand-in, the player), the edge stage
#: that cuts its clouds down to the tether, and the arm.
VEHICLE = ("player", "edge", "sim")
#: The share of the tether the camera's reduced clouds may take: the rest carries the arm's
#: state and commands, the gate's messages and room for the clouds' bursts. At 20 Mbit/s on
#: the sample, 0.6 (150 kB frames) put camera frame to decision at p50/p99 83/490 ms, the
#: link's queue overflowing into retransmissions; 0.4 at 55/153 ms.
CLOUD_SHARE = 0.4


def _run(*args: str) -> None:
    done = subprocess.run(args, capture_output=True, text=True)
    if done.returncode:
        raise OSError(f"{' '.join(args)}: {done.stderr.strip() or done.returncode}")


@dataclass
class Tether:
    """The namespace and the shaped pair; a context manager that makes and removes them.

    mbit : the bandwidth each way, Mbit/s; ``name`` names the namespace and both ends.
    """

    mbit: float
    name: str = field(default_factory=lambda: f"wgt{os.getpid() % 100000}")
    subnet: int = field(default_factory=lambda: os.getpid() % 250 + 1)
    samples: list[tuple[float, int, int]] = field(default_factory=list)  # (s, rx, tx bytes)
    _stop: threading.Event = field(default_factory=threading.Event)

    @property
    def topside_ip(self) -> str:
        return f"10.213.{self.subnet}.1"

    @property
    def vehicle_ip(self) -> str:
        return f"10.213.{self.subnet}.2"

    @property
    def topside_end(self) -> str:
        return f"{self.name}t"

    @property
    def vehicle_end(self) -> str:
        return f"{self.name}v"

    def check(self) -> None:
        """Raise ValueError saying why this tether cannot be made here."""
        if not self.mbit > 0:
            raise ValueError(f"--tether {self.mbit:g}: the bandwidth must be > 0 Mbit/s")
        if os.geteuid() != 0:
            raise ValueError("--tether needs root (it makes a network namespace and a veth "
                             "pair)")

    def __enter__(self) -> Tether:
        self.check()
        ns, top, veh = self.name, self.topside_end, self.vehicle_end
        self._remove()  # what a previous run left behind (killed before it could clean up)
        try:
            _run("ip", "netns", "add", ns)
            _run("ip", "link", "add", top, "type", "veth", "peer", "name", veh)
            _run("ip", "link", "set", veh, "netns", ns)
            _run("ip", "addr", "add", f"{self.topside_ip}/30", "dev", top)
            _run("ip", "link", "set", top, "up")
            _run("ip", "-n", ns, "addr", "add", f"{self.vehicle_ip}/30", "dev", veh)
            _run("ip", "-n", ns, "link", "set", veh, "up")
            _run("ip", "-n", ns, "link", "set", "lo", "up")
            shape = ["root", "tbf", "rate", f"{self.mbit}mbit", "burst", "64kb",
                     "latency", "100ms"]
            _run("tc", "qdisc", "add", "dev", top, *shape)
            _run("ip", "netns", "exec", ns, "tc", "qdisc", "add", "dev", veh, *shape)
        except OSError:
            self.__exit__()
            raise
        threading.Thread(target=self._count, daemon=True, name="tether-bytes").start()
        return self

    def __exit__(self, *_exc: object) -> None:
        self._stop.set()
        self._remove()

    def cut(self, down: bool = True) -> None:
        """Cut the tether (its topside end down: nothing crosses either way) or, with
        ``down`` False, join it again."""
        _run("ip", "link", "set", self.topside_end, "down" if down else "up")

    def _remove(self) -> None:
        """The namespace (with the vehicle's end) and the topside end, if they are there."""
        subprocess.run(["ip", "netns", "del", self.name], capture_output=True)
        subprocess.run(["ip", "link", "del", self.topside_end], capture_output=True)

    def _bytes(self) -> tuple[int, int]:
        """Bytes received and sent by the topside end so far."""
        stats = Path("/sys/class/net") / self.topside_end / "statistics"
        try:
            return (int((stats / "rx_bytes").read_text()), int((stats / "tx_bytes").read_text()))
        except OSError:  # removed
            return (0, 0)

    def _count(self) -> None:
        while not self._stop.wait(1.0 if self.samples else 0.0):
            self.samples.append((time.monotonic(), *self._bytes()))

    def traffic(self) -> dict[str, float]:
        """Mbit/s from the vehicle (up: the camera, the arm's state) and to it (down), mean
        and the highest of any second, over the run so far."""
        s = self.samples
        if len(s) < 2:
            return {}
        span = s[-1][0] - s[0][0]
        per_s = [((b[1] - a[1]) * 8e-6 / (b[0] - a[0]), (b[2] - a[2]) * 8e-6 / (b[0] - a[0]))
                 for a, b in zip(s, s[1:], strict=False)]
        return {"mbit": self.mbit, "seconds": round(span, 1),
                "up_mean_mbit_s": round((s[-1][1] - s[0][1]) * 8e-6 / span, 2),
                "down_mean_mbit_s": round((s[-1][2] - s[0][2]) * 8e-6 / span, 2),
                "up_peak_mbit_s": round(max(u for u, _ in per_s), 2),
                "down_peak_mbit_s": round(max(d for _, d in per_s), 2)}


def across_tether(services: dict[str, ComposeService], tether: Tether, port: int) -> None:
    """Put the vehicle's services in the tether's namespace with a router of their own on
    ``port`` there, which the topside router reaches across the tether, and which never
    sends the camera's full clouds across it; the player waits for the edge stage."""
    router = services["router"]
    vehicle_router = replace(router, name="vehicle-router", environment={
        **router.environment, "WAVEGRASP_NETNS": tether.name,
        "ZENOH_LISTEN": f"tcp/127.0.0.1:{port},tcp/{tether.vehicle_ip}:{port}",
        "WAVEGRASP_HOLD_KEYS": CAMERA_KEY,
        "WAVEGRASP_HOLD_INTERFACES": tether.vehicle_end})
    router.environment["WAVEGRASP_ROUTER_CONNECT"] = f"tcp/{tether.vehicle_ip}:{port}"
    router.depends_on = {**router.depends_on, "vehicle-router": "service_started"}
    services["vehicle-router"] = vehicle_router
    for name in VEHICLE:
        if name in services:
            services[name].environment.update({
                "WAVEGRASP_NETNS": tether.name, "ZENOH_CONNECT": f"tcp/127.0.0.1:{port}"})
    player = services.get("player")
    if player is not None and "edge" in services:
        player.depends_on = {**player.depends_on, "edge": "service_healthy"}
        waits = player.environment.get("WAVEGRASP_WAIT_FOR", "")
        player.environment["WAVEGRASP_WAIT_FOR"] = ",".join(filter(None, [waits, "edge"]))

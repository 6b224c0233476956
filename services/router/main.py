"""``wavegrasp router``: a zenoh session in router mode with explicit endpoints.

Listens on ``ZENOH_LISTEN`` (default ``tcp/127.0.0.1:7447``; compose uses ``tcp/0.0.0.0:7447``),
multicast scouting off. ``--config`` or ``ZENOH_CONFIG`` may name a JSON5 file (access control,
TLS: see ops/zenoh/) whose settings are applied first. ``--keys DIR`` (``WAVEGRASP_KEYS``)
first makes this installation's logins and certificates there if it holds none
(``wavegrasp keys``): compose's router does, on the first ``up``.
"""

from __future__ import annotations

import argparse
import logging
import os
import signal
import sys
import threading
from pathlib import Path

from wavegrasp.ops.keys import make_keys
from wavegrasp.runtime.bus import Bus, open_session
from wavegrasp.runtime.heartbeat import Heartbeat
from wavegrasp.runtime.service import setup_logging
from wavegrasp.runtime.settings import Settings, split_endpoints

log = logging.getLogger("wavegrasp.router")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="wavegrasp router", description=__doc__)
    parser.add_argument("--listen", help="endpoints, comma-separated (default: ZENOH_LISTEN)")
    parser.add_argument("--config", help="zenoh JSON5 config file (default: ZENOH_CONFIG)")
    parser.add_argument("--keys", type=Path, default=os.environ.get("WAVEGRASP_KEYS") or None,
                        help="make the logins and certificates in this folder first if it "
                        "holds none (default: WAVEGRASP_KEYS)")
    args = parser.parse_args(argv)
    settings = Settings.from_env("router", zenoh_mode="router", zenoh_config=args.config,
                                 zenoh_listen=split_endpoints(args.listen) if args.listen else None)
    if not settings.zenoh_listen:
        settings.zenoh_listen = ["tcp/127.0.0.1:7447"]
    if settings.hold_keys and not settings.hold_interfaces:
        print("wavegrasp router: WAVEGRASP_HOLD_KEYS needs WAVEGRASP_HOLD_INTERFACES (the "
              "interfaces to hold them off: the tether's)", file=sys.stderr)
        return 2
    setup_logging(settings.log_level)
    if args.keys is not None and not (args.keys / "credentials.txt").exists():
        try:
            made = make_keys(args.keys, [])
        except (OSError, ValueError) as exc:
            print(f"wavegrasp router: --keys {args.keys}: {exc}", file=sys.stderr)
            return 2
        log.info("made this installation's logins and certificates: %d files in %s",
                 len(made), args.keys)
    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())
    try:
        session = open_session(settings)
    except (ConnectionError, ValueError) as exc:  # each names the endpoints or the file
        print(f"wavegrasp {exc}", file=sys.stderr)
        return 2
    bus = Bus(settings, session=session)
    bus.declare_alive()
    log.info("router listening on %s", ", ".join(settings.zenoh_listen))
    heartbeat = Heartbeat(settings.health_file)
    heartbeat.beat(bus)
    while not stop.wait(heartbeat.period_s):
        heartbeat.beat(bus)
    bus.close()
    return 0

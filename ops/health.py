"""``wavegrasp health NAME``: exit 0 if service NAME holds its liveliness token, 1 if not.

Asks the router, from any host that reaches it, as a client that binds no port. (Compose's
healthchecks read each container's heartbeat file instead: services/runtime/heartbeat.py.)"""

from __future__ import annotations

import argparse
import sys

from wavegrasp.runtime.bus import Bus
from wavegrasp.runtime.settings import Settings


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="wavegrasp health", description=__doc__)
    parser.add_argument("service")
    parser.add_argument("--timeout", type=float, default=2.0)
    args = parser.parse_args(argv)
    settings = Settings.from_env("health-check", connect_timeout_s=args.timeout)
    if args.service == "router" and settings.zenoh_listen:
        # Run beside the router (its container sets ZENOH_LISTEN): connect to where it
        # listens. A router's liveliness is visible from any session that reaches it.
        settings.zenoh_connect = [e.replace("0.0.0.0", "127.0.0.1") for e in
                                  settings.zenoh_listen]
    settings.zenoh_listen = []  # a client only: never bind the port the service holds
    try:
        bus = Bus(settings)
    except ConnectionError as exc:
        print(exc, file=sys.stderr)
        return 1
    try:
        alive = args.service in bus.alive_services(timeout_s=args.timeout)
    finally:
        bus.close()
    print(f"{args.service}: {'alive' if alive else 'not alive'}")
    return 0 if alive else 1

"""``wavegrasp router``: a zenoh session in router mode with explicit endpoints.

Listens on ``ZENOH_LISTEN`` (default ``tcp/127.0.0.1:7447``; compose uses ``tcp/0.0.0.0:7447``),
multicast scouting off. ``ZENOH_CONFIG`` may name a JSON5 file (access control, TLS: see ops/)
whose settings are applied first.
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import signal
import sys
import threading

import zenoh

from wavegrasp.runtime.bus import Bus, zenoh_config
from wavegrasp.runtime.service import setup_logging
from wavegrasp.runtime.settings import Settings, split_endpoints

log = logging.getLogger("wavegrasp.router")


def router_config(settings: Settings, config_file: str | None) -> zenoh.Config:
    """The router's zenoh config: ``config_file`` (if any) with our endpoints on top."""
    if not config_file:
        return zenoh_config(settings)
    try:
        conf = zenoh.Config.from_file(config_file)
    except (zenoh.ZError, OSError) as exc:
        raise ValueError(f"{config_file}: not a usable zenoh config: {exc}") from None
    conf.insert_json5("mode", '"router"')
    conf.insert_json5("listen/endpoints", json.dumps(settings.zenoh_listen))
    conf.insert_json5("scouting/multicast/enabled", "false")
    conf.insert_json5("transport/shared_memory/enabled", "false")
    return conf


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="wavegrasp router", description=__doc__)
    parser.add_argument("--listen", help="endpoints, comma-separated (default: ZENOH_LISTEN)")
    parser.add_argument("--config", default=os.environ.get("ZENOH_CONFIG"),
                        help="zenoh JSON5 config file (default: ZENOH_CONFIG)")
    args = parser.parse_args(argv)
    settings = Settings.from_env("router", zenoh_mode="router",
                                 zenoh_listen=split_endpoints(args.listen) if args.listen else None)
    if not settings.zenoh_listen:
        settings.zenoh_listen = ["tcp/127.0.0.1:7447"]
    setup_logging(settings.log_level)
    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())
    try:
        session = zenoh.open(router_config(settings, args.config))
    except (zenoh.ZError, ValueError) as exc:
        print(f"wavegrasp router: cannot listen on {', '.join(settings.zenoh_listen)}: {exc}",
              file=sys.stderr)
        return 2
    bus = Bus(settings, session=session)
    bus.declare_alive()
    log.info("router listening on %s", ", ".join(settings.zenoh_listen))
    stop.wait()
    bus.close()
    return 0

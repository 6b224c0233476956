"""What ``wavegrasp up`` checks of a run's choices before anything starts, so a mistake
gets one line and exit code 2 (the launcher turns the ValueError into it)."""

from __future__ import annotations

import argparse
import importlib
import socket
from collections.abc import Mapping

from wavegrasp.arm import ArmModel
from wavegrasp.predictor import MODELS


def check_choices(args: argparse.Namespace, environ: Mapping[str, str]) -> None:
    """Raise ValueError naming the first of the run's choices that cannot work: a predictor
    that does not exist, an arm description that does not load, a port taken; ImportError
    for a system library that open3d cannot load."""
    # open3d loads system libraries (libusb...): a missing one is named in one line (the
    # command's handler, wavegrasp.cli) before any service starts and fails on it.
    importlib.import_module("open3d")
    if args.predictor and args.predictor not in MODELS:
        raise ValueError(f"--predictor {args.predictor}: no such predictor (there are "
                         f"{', '.join(MODELS)})")
    urdf = environ.get("WAVEGRASP_ARM_URDF")
    if urdf:
        try:
            ArmModel.load(urdf)
        except (OSError, ValueError) as exc:
            raise ValueError(f"WAVEGRASP_ARM_URDF: {exc}") from None
    ports = {"--viewer-port": args.viewer_port} if args.viewer else {}
    if args.foxglove:
        ports["--foxglove-port"] = args.foxglove_port
    if environ.get("WAVEGRASP_ROUTER_PORT"):
        text = environ["WAVEGRASP_ROUTER_PORT"]
        if not text.isdigit() or not 0 < int(text) < 65536:
            raise ValueError(f"WAVEGRASP_ROUTER_PORT {text!r}: not a port number")
        ports["WAVEGRASP_ROUTER_PORT"] = int(text)
    for what, port in ports.items():
        with socket.socket() as s:
            try:
                s.bind((environ.get("WAVEGRASP_ROUTER_BIND", "127.0.0.1"), port))
            except OSError as exc:
                raise ValueError(f"{what} {port}: the port is taken ({exc.strerror}): "
                                 "choose another") from None

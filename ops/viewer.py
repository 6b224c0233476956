"""``wavegrasp viewer``: rerun's web viewer, fed live by the recorder.

Runs the rerun CLI of the pinned SDK as a gRPC server that SDKs log to (the recorder, with
``WAVEGRASP_VIEWER_URL=rerun+http://HOST:PORT/proxy``) and serves the web viewer over HTTP;
open the printed address in a browser. Rerun's usage reporting is switched off first (the CLI
otherwise turns it on in the home folder). Listens on ``--bind`` only: 127.0.0.1 by default,
the compose file's viewer service binds its container's address.
"""

from __future__ import annotations

import argparse
import os
import shutil
import subprocess
import sys
from pathlib import Path


def rerun_cli() -> str:
    """The rerun executable installed with the SDK (beside this interpreter, else on PATH)."""
    beside = Path(sys.executable).parent / "rerun"
    found = str(beside) if beside.exists() else shutil.which("rerun")
    if found is None:
        raise FileNotFoundError("no rerun executable: install rerun-sdk")
    return found


def viewer_url(web_port: int, grpc_port: int, host: str = "127.0.0.1") -> str:
    """The address a browser opens: the web viewer, connected to the gRPC proxy."""
    return f"http://{host}:{web_port}/?url=rerun%2Bhttp://{host}:{grpc_port}/proxy"


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="wavegrasp viewer", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--bind", default="127.0.0.1", help="address to listen on")
    p.add_argument("--port", type=int, default=9876, help="gRPC port the recorder logs to")
    p.add_argument("--web-port", type=int, default=9090, help="HTTP port of the web viewer")
    a = p.parse_args(argv)
    try:
        cli = rerun_cli()
    except FileNotFoundError as exc:
        print(f"wavegrasp viewer: {exc}", file=sys.stderr)
        return 2
    subprocess.run([cli, "analytics", "disable"], check=False, stdout=subprocess.DEVNULL,
                   stderr=subprocess.DEVNULL)
    host = "127.0.0.1" if a.bind in ("0.0.0.0", "::") else a.bind  # noqa: S104
    print(f"wavegrasp viewer: open {viewer_url(a.web_port, a.port, host)}", flush=True)
    os.execv(cli, [cli, "--serve-web", "--bind", a.bind, "--port", str(a.port),
                   "--web-viewer-port", str(a.web_port)])


if __name__ == "__main__":
    raise SystemExit(main())

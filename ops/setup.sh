#!/usr/bin/env bash
# Set up wavegrasp on a fresh Debian/Ubuntu machine: system library, virtualenv, package.
# Idempotent; the virtualenv goes to .venv beside this checkout (override with VENV=...).
set -euo pipefail
cd "$(dirname "$0")/.."
VENV=${VENV:-.venv}
if ! ldconfig -p 2>/dev/null | grep -q libusb-1.0.so.0; then
  # open3d imports only with libusb present.
  SUDO=$([ "$(id -u)" = 0 ] && echo "" || echo sudo)
  $SUDO apt-get update -qq
  DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq libusb-1.0-0 >/dev/null
fi
[ -x "$VENV/bin/python" ] || python3 -m venv "$VENV"
"$VENV/bin/python" -m pip install -q --upgrade pip
"$VENV/bin/python" -m pip install -q -e ".[dev,cluster]"
# The tests check our CDR with an independent decoder (Foxglove's TypeScript one) under node.
if ! command -v npm >/dev/null; then
  SUDO=$([ "$(id -u)" = 0 ] && echo "" || echo sudo)
  $SUDO apt-get update -qq
  DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq nodejs npm >/dev/null
fi
[ -d tests/ros2_decode/node_modules/@foxglove/rosmsg2-serialization ] ||
  npm ci --prefix tests/ros2_decode --no-audit --no-fund --silent
echo "wavegrasp is set up in $VENV" >&2

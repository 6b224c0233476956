#!/usr/bin/env bash
# bash ops/compose-test.sh RECORDING OUTDIR
#
# Builds the wavegrasp image and runs `docker-compose up` on RECORDING to its end, leaving
# run.mcap and summary.json in OUTDIR; exits non-zero unless every container exited 0.
# On a Debian machine without Docker (as root, or with sudo) it installs Debian's docker.io,
# docker-compose and debootstrap, starts dockerd if none answers, and makes the Debian base
# image from Debian's archive with debootstrap (for machines that cannot reach Docker Hub).
#
# Environment: WAVEGRASP_PACE (default realtime), WAVEGRASP_BASE_IMAGE (a Debian bookworm
# image to build on instead, e.g. debian:bookworm-slim), WAVEGRASP_BUILD_CA (a CA bundle the
# build's pip must trust; default: the system's, passed as a BuildKit secret, never stored in
# the image), WAVEGRASP_COMPOSE_PROJECT (default wavegrasp-test), DEBIAN_MIRROR.
set -euo pipefail
if [ $# -ne 2 ]; then
  echo "usage: bash ops/compose-test.sh RECORDING OUTDIR" >&2
  exit 2
fi
cd "$(dirname "$0")/.."
recording=$(realpath "$1")
[ -f "$recording" ] || { echo "compose-test: $1: no such recording file" >&2; exit 2; }
mkdir -p "$2"
outdir=$(realpath "$2")
SUDO=$([ "$(id -u)" = 0 ] && echo "" || echo sudo)
log() { echo "compose-test: $*" >&2; }

# --- Docker, docker-compose and debootstrap -----------------------------------------------
# Debian's docker.io client: a newer client elsewhere on PATH may lack the BuildKit builder.
DOCKER=/usr/bin/docker
if [ ! -x $DOCKER ] || ! command -v docker-compose >/dev/null \
    || { [ -z "${WAVEGRASP_BASE_IMAGE:-}" ] && ! command -v debootstrap >/dev/null; }; then
  log "installing docker.io, docker-compose and debootstrap"
  $SUDO apt-get update -qq
  DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq docker.io docker-compose \
    debootstrap >/dev/null
fi
if ! $DOCKER info >/dev/null 2>&1; then
  dockerd_log=${TMPDIR:-/tmp}/wavegrasp-dockerd.log
  rt_flag=()
  # A cgroup v1 kernel that schedules real-time by group gives containers no real-time
  # runtime unless dockerd has some to hand out (compose's cpu_rt_runtime).
  if [ -f /sys/fs/cgroup/cpu/cpu.rt_runtime_us ]; then
    rt_flag=(--cpu-rt-runtime=900000)
    rt_dockerd=1
  fi
  log "starting dockerd (log: $dockerd_log)"
  $SUDO sh -c "nohup /usr/sbin/dockerd ${rt_flag[*]} >'$dockerd_log' 2>&1 &"
  for _ in $(seq 60); do $DOCKER info >/dev/null 2>&1 && break; sleep 0.5; done
  $DOCKER info >/dev/null 2>&1 || { log "dockerd did not start; see $dockerd_log"; exit 1; }
fi
files=(-f docker-compose.yml)
docker_rt=$(cat /sys/fs/cgroup/cpu/docker/cpu.rt_runtime_us 2>/dev/null || echo 0)
if [ -n "${rt_dockerd:-}" ] || [ "$docker_rt" -ge 900000 ]; then
  # Six containers on the real-time path share dockerd's 900 ms per second.
  files+=(-f ops/compose-rt-cgroup-v1.yml)
fi

if ! (ulimit -Hr 99) 2>/dev/null; then
  # Without CAP_SYS_RESOURCE (some sandboxes) runc cannot raise the rtprio limit and would
  # refuse to start the containers; the path's services then warn and use the normal policy.
  export WAVEGRASP_RTPRIO_LIMIT=${WAVEGRASP_RTPRIO_LIMIT:-$(ulimit -Hr)}
fi

# --- The base image and the wavegrasp image ----------------------------------------------
base=${WAVEGRASP_BASE_IMAGE:-wavegrasp-base:bookworm}
if ! $DOCKER image inspect "$base" >/dev/null 2>&1; then
  if [ -n "${WAVEGRASP_BASE_IMAGE:-}" ]; then
    $DOCKER pull "$base"
  else
    mirror=${DEBIAN_MIRROR:-http://deb.debian.org/debian}
    rootfs=$(mktemp -d)
    log "making $base with debootstrap from $mirror"
    $SUDO debootstrap --variant=minbase bookworm "$rootfs" "$mirror" >/dev/null
    $SUDO tee "$rootfs/etc/apt/sources.list" >/dev/null <<EOF
deb $mirror bookworm main
deb $mirror bookworm-updates main
deb ${mirror%/debian}/debian-security bookworm-security main
EOF
    $SUDO sh -c "rm -rf '$rootfs'/var/cache/apt/archives/*.deb '$rootfs'/var/lib/apt/lists/*"
    $SUDO tar -C "$rootfs" -c . | $DOCKER import -c 'CMD ["/bin/bash"]' - "$base" >/dev/null
    $SUDO rm -rf "$rootfs"
  fi
fi
ca=${WAVEGRASP_BUILD_CA:-/etc/ssl/certs/ca-certificates.crt}
secret=()
[ -s "$ca" ] && secret=(--secret "id=pip_cert,src=$ca")
log "building wavegrasp:latest on $base"
previous=$($DOCKER image inspect -f '{{.Id}}' wavegrasp:latest 2>/dev/null || true)
DOCKER_BUILDKIT=1 $DOCKER build -q --build-arg "BASE=$base" "${secret[@]}" \
  -f ops/Dockerfile -t wavegrasp:latest . >/dev/null
# Each rebuild after a change leaves the last image untagged (about 2 GB); repeated runs on one
# machine would fill its disk.
if [ -n "$previous" ] && [ "$previous" != "$($DOCKER image inspect -f '{{.Id}}' wavegrasp:latest)" ]; then
  $DOCKER image rm "$previous" >/dev/null 2>&1 || true
fi
log "image: $($DOCKER image inspect -f '{{.Size}}' wavegrasp:latest | awk '{printf "%.0f MB", $1/1e6}')"

# --- docker-compose up on the recording ---------------------------------------------------
export WAVEGRASP_RECORDINGS=$(dirname "$recording")
export WAVEGRASP_RECORDING=recordings/$(basename "$recording")
export WAVEGRASP_RUNS=$outdir WAVEGRASP_OUT=/runs
export WAVEGRASP_ROUTER_PUBLISH=127.0.0.1:$(python3 -c \
  'import socket; s = socket.socket(); s.bind(("127.0.0.1", 0)); print(s.getsockname()[1])')
compose=(docker-compose -p "${WAVEGRASP_COMPOSE_PROJECT:-wavegrasp-test}" "${files[@]}")
trap '"${compose[@]}" down --volumes --remove-orphans >/dev/null 2>&1 || true' EXIT
log "docker-compose up on $recording -> $outdir (pace ${WAVEGRASP_PACE:-realtime})"
"${compose[@]}" up --no-build --abort-on-container-exit --exit-code-from player
failed=0
for id in $("${compose[@]}" ps -q); do
  read -r name code < <($DOCKER inspect -f '{{.Name}} {{.State.ExitCode}}' "$id")
  log "${name#/} exited $code"
  [ "$code" = 0 ] || failed=1
done
for f in run.mcap summary.json; do
  [ -s "$outdir/$f" ] || { log "$outdir/$f is missing"; failed=1; }
done
exit $failed

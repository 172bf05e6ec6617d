#!/usr/bin/env bash
# A swarm across several "hosts" on this machine: Linux network namespaces joined by veth
# pairs and a bridge (10.77.0.0/24), the router, the world, the server and each agent on
# a host of its own, links impaired as asked; writes the usual run folder to --out.
#
#   sudo scripts/multihost.sh --out runs/mh [--robots N] [--clock lockstep|realtime]
#        [--delay-ms D [--jitter-ms J] [--delay-spread-ms S]] [--loss P] [--duration S] [--rate-mbit R] [--seed N]
#        [--set FIELD=VALUE] [--no-report]
#
# Needs root (ip netns, iptables, tc).  Everything it made (namespaces, veths, processes) is
# removed on exit, on failure and on Ctrl-C.  Any flag of tagswarm up's scenario and network
# groups works too (--scenario, --zenoh-lease-ms ...).  Docs: docs/multihost.md.
set -euo pipefail
ROOT="$(cd "$(dirname "$0")/.." && pwd)"
# the project's virtualenv (scripts/setup.sh) unless TAGSWARM_PYTHON names another interpreter
PY="${TAGSWARM_PYTHON:-$ROOT/.venv/bin/python}"
[ -x "$PY" ] || PY=python3
exec "$PY" -m tagswarm.deploy.multihost "$@"

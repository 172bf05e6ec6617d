#!/usr/bin/env bash
# Set up and run the main demo; the result lands in runs/.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
exec .venv/bin/tagswarm snapshot "$@"

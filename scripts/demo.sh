#!/usr/bin/env bash
# Set up and run the main demo: 4 robots for a simulated minute; results in runs/<time>/.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
exec .venv/bin/tagswarm up "$@"

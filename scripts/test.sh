#!/usr/bin/env bash
# Set up, lint, type-check and run every test (unit, integration, end-to-end).
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
.venv/bin/ruff check .
.venv/bin/mypy
.venv/bin/python -m pytest -q --durations=15 "$@"

#!/usr/bin/env bash
# Set up, lint, type-check and run every test (unit, integration, end-to-end).
# With arguments, they go to one plain pytest run (e.g. `bash scripts/test.sh -m "not e2e"`).
# Without, two passes: unit tests and lockstep runs on TAGSWARM_TEST_WORKERS (default 2) pytest-xdist
# workers, a module per worker at a time, then the tests marked `serial` (wall-clock ones) alone.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
.venv/bin/ruff check .
.venv/bin/mypy
if [ "$#" -gt 0 ]; then
  exec .venv/bin/python -m pytest -q --durations=15 "$@"
fi
rc=0 serial_rc=0
.venv/bin/python -m pytest -q --durations=15 -n "${TAGSWARM_TEST_WORKERS:-2}" --dist loadfile -m "not serial" || rc=$?
.venv/bin/python -m pytest -q --durations=15 -m serial || serial_rc=$?
if [ "$rc" -eq 0 ]; then rc=$serial_rc; fi
if [ "$rc" -ne 0 ]; then
  echo "test.sh: a test pass failed (exit $rc)" >&2
fi
exit "$rc"

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
# both passes are also kept in a log, so that a failure's assertion can be repeated at the very end
# (a long log is often seen only by its head and tail); wide lines keep the short summary's message whole
log=$(mktemp)
trap 'rm -f "$log"' EXIT
export COLUMNS=${COLUMNS:-200}
.venv/bin/python -m pytest -q --durations=15 -n "${TAGSWARM_TEST_WORKERS:-2}" --dist loadfile -m "not serial" \
  2>&1 | tee -a "$log" || rc=$?
.venv/bin/python -m pytest -q --durations=15 -m serial 2>&1 | tee -a "$log" || serial_rc=$?
if [ "$rc" -eq 0 ]; then rc=$serial_rc; fi
if [ "$rc" -ne 0 ]; then
  echo "test.sh: what failed, repeated from both passes:" >&2
  grep -E '^(FAILED|ERROR) |^E  ' "$log" | cut -c1-600 | head -n 80 >&2 || true
  echo "test.sh: a test pass failed (exit $rc)" >&2
fi
exit "$rc"

#!/usr/bin/env bash
# Create .venv and install tagswarm with its pinned dependencies (idempotent).
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PYTHON:-python3}
if [ ! -x .venv/bin/python ]; then
  "$PY" -m venv .venv
fi
stamp=.venv/.tagswarm-installed
if [ ! -f "$stamp" ] || [ pyproject.toml -nt "$stamp" ]; then
  .venv/bin/python -m pip install -q --upgrade pip
  .venv/bin/python -m pip install -q -e '.[dev]'
  touch "$stamp"
fi
# The browser test (tests/e2e/test_view.py) drives Debian's Chromium through Playwright
# (executable_path=/usr/bin/chromium, so Playwright never downloads a browser of its own).
if [ ! -x /usr/bin/chromium ]; then
  if command -v apt-get >/dev/null 2>&1 && [ "$(id -u)" -eq 0 ]; then
    echo "setup: installing Debian's chromium for the browser test (apt-get)"
    apt_log=$(mktemp)
    if ! { apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq chromium fonts-dejavu-core; } \
        >"$apt_log" 2>&1; then
      tail -n 5 "$apt_log" >&2
      echo "setup: could not install chromium; tests/e2e/test_view.py will be skipped (fails under CI=true)" >&2
    fi
    rm -f "$apt_log"
  else
    echo "setup: /usr/bin/chromium is missing and apt-get is unavailable (or not root): install Debian's" \
         "chromium to run the browser test (tests/e2e/test_view.py is skipped without it)" >&2
  fi
fi

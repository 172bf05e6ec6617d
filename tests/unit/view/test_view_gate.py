"""The browser tests' gate (tests/e2e/test_view.py): without Chromium or Playwright they are
skipped with the reason, but under CI (``CI`` set) they fail, and only they: the module
still collects, so the rest of the session runs."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[3]
MODULE = "tests/e2e/test_view.py"
# playwright made unimportable in the child (a None entry in sys.modules makes the import fail)
NO_PLAYWRIGHT = "import sys; sys.modules['playwright'] = None; import pytest; sys.exit(pytest.main(sys.argv[1:]))"


def _pytest(*args: str, ci: bool, chromium: str, playwright: bool = True) -> subprocess.CompletedProcess[str]:
    env = {k: v for k, v in os.environ.items() if k != "CI"} | {"VIEW_TEST_CHROMIUM": chromium}
    if ci:
        env["CI"] = "true"
    head = [sys.executable, "-m", "pytest"] if playwright else [sys.executable, "-c", NO_PLAYWRIGHT]
    return subprocess.run([*head, "-p", "no:cacheprovider", "-q", "-rsf", *args], cwd=ROOT, env=env,
                          capture_output=True, text=True, timeout=120)


@pytest.mark.parametrize("playwright", [True, False], ids=["no-chromium", "no-playwright"])
def test_a_missing_browser_fails_only_the_browser_tests_under_ci(playwright: bool) -> None:
    chromium = "/nonexistent/chromium" if playwright else sys.executable  # some file that exists
    why = "is not installed" if playwright else "playwright is not importable"
    res = _pytest(MODULE, "-k", "browser", ci=True, chromium=chromium, playwright=playwright)
    out = res.stdout + res.stderr
    # the module collected (the other test is only deselected) and the browser test alone errs at setup
    assert res.returncode == 1 and out.splitlines()[-1].startswith("1 deselected, 1 error"), out
    assert "ERROR at setup of test_browser_view_of_a_running_system" in out and "during collection" not in out, out
    assert "browser test cannot run under CI" in out and why in out, out


@pytest.mark.parametrize("playwright", [True, False], ids=["no-chromium", "no-playwright"])
def test_a_missing_browser_skips_with_the_reason_outside_ci(playwright: bool) -> None:
    chromium = "/nonexistent/chromium" if playwright else sys.executable
    why = "/nonexistent/chromium is not installed" if playwright else "playwright is not importable"
    res = _pytest(MODULE, "-k", "browser", ci=False, chromium=chromium, playwright=playwright)
    out = res.stdout + res.stderr
    assert res.returncode == 0 and "1 skipped" in out and "SKIPPED" in out and why in out, out

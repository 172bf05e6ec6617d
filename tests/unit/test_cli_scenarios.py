"""``tagswarm scenarios``: the list, its --help (it printed the list), and stray arguments."""

from __future__ import annotations

import pytest

from tagswarm.cli import main
from tagswarm.protocol.scenario import builtin_descriptions


def test_scenarios_lists_every_builtin_and_help_explains(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["scenarios"]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert [ln.split()[0] for ln in lines] == list(builtin_descriptions())
    assert main(["scenarios", "--help"]) == 0
    out = capsys.readouterr().out
    assert out.startswith("usage: tagswarm scenarios") and "--scenario" in out and "hall " not in out
    assert main(["scenarios", "hall"]) == 2
    err = capsys.readouterr().err.strip()
    assert err == "tagswarm scenarios: error: scenarios takes no arguments, got 'hall'"

"""One error root: every exception class of the project derives from TagswarmError, usage
errors from UsageError, and run_main (the one boundary) turns exactly those into exit code 2
with one line."""

from __future__ import annotations

import ast
import importlib
import os
from pathlib import Path

import pytest

from tagswarm.protocol.errors import TagswarmError, UsageError
from tagswarm.runtime.process import run_main

PACKAGE = Path(__file__).resolve().parents[2] / "tagswarm"
#: the classes a user's bad input raises (exit 2); every other project error is handled where it arises
USAGE = {"ConfigError", "ScenarioError", "KeyNameError", "BusError", "JournalError", "RunFolderError",
         "RecordingError", "UsageError",
         "NoSubscriberError",  # a command nobody reads (wrong run/network)
         "SwarmScenarioError"}  # the testing fixture's scenario does not load


def _exception_classes() -> dict[str, type[BaseException]]:
    """Every class named ``*Error``/``Rejected`` or deriving from an exception, defined in the
    package (links followed), by name."""
    found: dict[str, type[BaseException]] = {}
    for folder, _, files in os.walk(PACKAGE, followlinks=True):
        for f in files:
            if not f.endswith(".py"):
                continue
            path = Path(folder, f)
            rel = path.relative_to(PACKAGE.parent).with_suffix("")
            module = ".".join(rel.parts).removesuffix(".__init__")
            for node in ast.parse(path.read_text()).body:
                if isinstance(node, ast.ClassDef):
                    obj = getattr(importlib.import_module(module), node.name)
                    if isinstance(obj, type) and issubclass(obj, BaseException):
                        assert node.name not in found, f"two exception classes called {node.name}"
                        found[node.name] = obj
    return found


def test_every_project_exception_has_the_one_root() -> None:
    classes = _exception_classes()
    assert {"DecodeError", "PlacementError", "CheckpointError", "Rejected", "TagswarmError"} | USAGE <= set(classes)
    assert [n for n, c in classes.items() if not issubclass(c, TagswarmError)] == []
    assert {n for n, c in classes.items() if issubclass(c, UsageError)} == USAGE


def test_errors_that_were_value_errors_still_are() -> None:
    classes = _exception_classes()
    for name in ("ConfigError", "ScenarioError", "KeyNameError", "JournalError", "RunFolderError", "PlacementError",
                 "CheckpointError"):
        assert issubclass(classes[name], ValueError), name


@pytest.mark.parametrize("name", sorted(USAGE))
def test_run_main_turns_a_usage_error_into_one_line_and_exit_2(name: str, capsys: pytest.CaptureFixture[str]) -> None:
    cls = _exception_classes()[name]

    def body() -> int:
        raise cls("bad thing\n  on two lines")

    assert run_main("prog", body) == 2
    assert capsys.readouterr().err == "prog: error: bad thing on two lines\n"


def test_run_main_lets_other_errors_through() -> None:
    from tagswarm.protocol.codec import DecodeError

    def body() -> int:
        raise DecodeError("malformed", "not for the user")

    with pytest.raises(DecodeError):
        run_main("prog", body)
    assert run_main("prog", lambda: 7) == 7

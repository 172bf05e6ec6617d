"""Markers by tier, from the directory a test lives in: tests/integration is marked
``integration`` (loopback Zenoh sessions in one process), tests/e2e ``e2e`` (real OS
processes).  ``pytest -m "not e2e"`` runs the unit and integration tiers."""

from __future__ import annotations

from pathlib import Path

import pytest

TESTS = Path(__file__).resolve().parent
TIERS = {"integration": pytest.mark.integration, "e2e": pytest.mark.e2e}


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    for item in items:
        path = Path(item.path).resolve()
        if path.is_relative_to(TESTS):
            mark = TIERS.get(path.relative_to(TESTS).parts[0])
            if mark is not None:
                item.add_marker(mark)

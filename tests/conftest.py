"""Markers by tier, from the directory a test lives in: tests/integration is marked
``integration`` (loopback Zenoh sessions in one process), tests/e2e ``e2e`` (real OS
processes).  ``pytest -m "not e2e"`` runs the unit and integration tiers.

``serial`` marks what must have the machine to itself: every integration test (in-process
sessions waiting on the wall clock) and the end-to-end modules in :data:`SERIAL_E2E`.
Everything else -- unit tests and lockstep runs, whose results do not depend on the load --
runs on two pytest-xdist workers (``scripts/test.sh``), a module at a time per worker so that
its module-scoped runs are made once."""

from __future__ import annotations

from pathlib import Path

import pytest

TESTS = Path(__file__).resolve().parent
TIERS = {"integration": pytest.mark.integration, "e2e": pytest.mark.e2e}
#: end-to-end modules that run against the wall clock: real-time runs (a loaded machine makes the
#: world fall behind), liveliness leases, killed and restarted processes, containers, replays paced
#: by the wall clock (test_replay: on a loaded machine a replayed server published one correction
#: more than the recorded one), and the modules that share one reference run through the plugin's
#: in-session cache (determinism, world restart)
SERIAL_E2E = frozenset({
    "test_agent_process", "test_agent_restart", "test_compose_containers", "test_determinism",
    "test_liveliness_lease", "test_multihost", "test_overload", "test_replay", "test_spy",
    "test_up_cleanup", "test_up_links", "test_world_restart",
})


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    for item in items:
        path = Path(item.path).resolve()
        if path.is_relative_to(TESTS):
            tier = path.relative_to(TESTS).parts[0]
            mark = TIERS.get(tier)
            if mark is not None:
                item.add_marker(mark)
            if tier == "integration" or (tier == "e2e" and path.stem in SERIAL_E2E):
                item.add_marker(pytest.mark.serial)

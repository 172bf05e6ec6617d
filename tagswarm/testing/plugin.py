"""The pytest plugin (entry point ``pytest11``: active wherever tagswarm is installed).

Fixture ``swarm``: a :class:`~tagswarm.testing.factory.SwarmFactory` whose runs live in
pytest's temporary directory and are all stopped when the test ends, passed or failed,
timed out (pytest-timeout) or interrupted.  Heavy imports wait until a test asks for it, so
the plugin costs other test suites nothing.  See docs/testing.md.
"""

from __future__ import annotations

from collections.abc import Iterator
from typing import TYPE_CHECKING, Any

import pytest

if TYPE_CHECKING:
    from tagswarm.testing.factory import SwarmFactory


@pytest.fixture(scope="session")
def tagswarm_run_cache() -> dict[Any, Any]:
    """Finished runs made with ``reuse=True``, shared by the tests of one session."""
    return {}


@pytest.fixture
def swarm(tmp_path_factory: pytest.TempPathFactory, tagswarm_run_cache: dict[Any, Any]) -> Iterator[SwarmFactory]:
    """Run swarms as real processes: ``run = swarm(scenario="paper", robots=4, seed=0, duration_s=20)``
    for a finished run, ``with swarm.start(...) as s:`` for a live one (docs/testing.md)."""
    from tagswarm.testing.factory import SwarmFactory

    factory = SwarmFactory(tmp_path_factory.mktemp, tagswarm_run_cache)
    try:
        yield factory
    finally:
        factory.close()

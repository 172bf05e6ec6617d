"""What :mod:`tagswarm.testing` raises: a process that died early, a wait that timed out,
bad arguments to the fixture.  Each message ends with the last lines of every process's
log, so a failing test says why without opening the run folder."""

from __future__ import annotations

from tagswarm.protocol.errors import TagswarmError
from tagswarm.protocol.scenario_schema import ScenarioError


class SwarmError(TagswarmError):
    """A swarm under test could not be started, driven or finished as asked."""


class SwarmProcessDied(SwarmError):
    """A process of the swarm exited on its own with a failure code (not one the test killed)."""

    def __init__(self, name: str, code: int | None, tails: str) -> None:
        self.name, self.code = name, code
        super().__init__(f"{name} exited with code {code}\n{tails}")


class SwarmTimeout(SwarmError, TimeoutError):
    """A wait for a condition (simulated time, a map, the end of the run) timed out."""


class SwarmScenarioError(SwarmError, ScenarioError):
    """The scenario asked of the fixture does not load (the message names the field); also a
    :class:`~tagswarm.protocol.scenario_schema.ScenarioError`."""

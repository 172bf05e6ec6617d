"""``tagswarm.testing``: run a whole swarm from a test, as real OS processes.

The pytest fixture ``swarm`` (:mod:`tagswarm.testing.plugin`, registered as a pytest plugin)
hands out a :class:`SwarmFactory`: ``swarm(...)`` returns a finished :class:`Run`,
``swarm.start(...)`` a :class:`LiveSwarm`.  Usage and reference: docs/testing.md.

Modules: ``options`` (what a test asks for -> scenario and command lines),
``live`` (the live handle), ``subscription``, ``result`` (the finished run),
``trajectories``, ``runfolder``, ``factory``, ``errors``, ``plugin``; the children's
process groups and the nets that take them down are :mod:`tagswarm.runtime.procgroup`.

Names are imported on first use, so loading the plugin does not load Zenoh or numpy.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from tagswarm.testing.errors import SwarmError, SwarmProcessDied, SwarmScenarioError, SwarmTimeout
    from tagswarm.testing.factory import SwarmFactory
    from tagswarm.testing.live import LiveSwarm
    from tagswarm.testing.options import NetFault
    from tagswarm.testing.result import Run
    from tagswarm.testing.subscription import Sample, Subscription

_WHERE = {"SwarmError": "errors", "SwarmProcessDied": "errors", "SwarmTimeout": "errors",
          "SwarmScenarioError": "errors",
          "SwarmFactory": "factory", "LiveSwarm": "live", "NetFault": "options", "Run": "result",
          "Sample": "subscription", "Subscription": "subscription"}
__all__ = ["LiveSwarm", "NetFault", "Run", "Sample", "Subscription", "SwarmError", "SwarmFactory",
           "SwarmProcessDied", "SwarmScenarioError", "SwarmTimeout"]


def __getattr__(name: str) -> Any:
    if name in _WHERE:
        return getattr(importlib.import_module(f"tagswarm.testing.{_WHERE[name]}"), name)
    raise AttributeError(f"module 'tagswarm.testing' has no attribute {name!r}")

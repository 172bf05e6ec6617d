"""The world process's one frozen config, built from scenario, environment and flags."""

from __future__ import annotations

import argparse
from collections.abc import Mapping, Sequence

import msgspec

from tagswarm.protocol.bus import BusConfig
from tagswarm.protocol.scenario import Scenario
from tagswarm.runtime.config import ConfigError, Invocation, OneLineParser, add_common_args


class WorldConfig(msgspec.Struct, frozen=True, kw_only=True):
    """Everything the world process needs; built once in ``main``."""

    scenario: Scenario
    bus: BusConfig
    run: str = "default"
    status_period_s: float = 1.0
    spawn_render_workers: bool = True
    log_level: str = "INFO"


def parser(prog: str = "tagswarm-world") -> argparse.ArgumentParser:
    p = OneLineParser(
        prog=prog,
        description="The tagswarm world: steps the pybullet arena, renders every robot's cameras and publishes "
        "images, encoder ticks, ground truth and the clock over Zenoh; takes wheel commands.",
    )
    add_common_args(p)
    p.add_argument("--render-workers", type=int, metavar="K",
                   help="render in K worker processes (0 = in this process); same as --set render.workers=K")
    p.add_argument("--no-spawn-workers", action="store_true",
                   help="do not start render workers; expect them to be started separately (compose)")
    p.add_argument("--status-period", type=float, default=1.0, metavar="SECONDS",
                   help="simulated seconds between status messages (default 1)")
    return p


def build_config(argv: Sequence[str] | None = None, environ: Mapping[str, str] | None = None) -> WorldConfig:
    """Parse flags and environment into a :class:`WorldConfig`; raises ConfigError /
    ScenarioError with a one-line message."""
    inv = Invocation(parser(), argv, environ)
    args = inv.args
    if args.render_workers is not None:
        if args.render_workers < 0:
            raise ConfigError("--render-workers must be >= 0")
        args.overrides.append(f"render.workers={args.render_workers}")
    scenario = inv.scenario()
    run = inv.run()
    if args.status_period <= 0:
        raise ConfigError("--status-period must be > 0")
    return WorldConfig(scenario=scenario, bus=inv.bus(), run=run, status_period_s=args.status_period,
                       spawn_render_workers=not args.no_spawn_workers, log_level=inv.log_level())

"""The server process's one frozen config."""

from __future__ import annotations

import argparse
from collections.abc import Mapping, Sequence

import msgspec

from protocol.bus import BusConfig
from protocol.config import ConfigError, OneLineParser, add_common_args, bus_from, env_of, parse, pick, scenario_from
from protocol.keys import Keys
from protocol.scenario import Scenario


class ServerConfig(msgspec.Struct, frozen=True, kw_only=True):
    scenario: Scenario
    bus: BusConfig
    run: str = "default"
    log_level: str = "INFO"
    map_rate_hz: float = 2.0
    update_rate_hz: float = 10.0
    lag_s: float = 30.0
    participant: str = "server/0"


def parser(prog: str = "tagswarm-server") -> argparse.ArgumentParser:
    p = OneLineParser(
        prog=prog,
        description="The tagswarm map server: stitches every robot's relative observations and odometry into one "
        "global map (paper stitching + GTSAM iSAM2 fixed-lag pose graph) and pushes map->odom corrections back.")
    add_common_args(p)
    p.add_argument("--map-rate", type=float, default=2.0, metavar="HZ", help="global map publish rate (default 2)")
    p.add_argument("--update-rate", type=float, default=10.0, metavar="HZ",
                   help="fusion updates per simulated second in realtime mode (default 10; lockstep: every tick)")
    p.add_argument("--lag", type=float, default=30.0, metavar="SECONDS",
                   help="fixed-lag window of the smoother in simulated seconds (default 30)")
    return p


def build_config(argv: Sequence[str] | None = None, environ: Mapping[str, str] | None = None) -> ServerConfig:
    args = parse(parser(), argv)
    env = env_of(environ)
    scenario = scenario_from(args, env)
    for name in ("map_rate", "update_rate", "lag"):
        if getattr(args, name) <= 0:
            raise ConfigError(f"--{name.replace('_', '-')} must be > 0")
    run = pick(args, env, "run", "default")
    Keys(run)
    return ServerConfig(scenario=scenario, bus=bus_from(args, env), run=run,
                        log_level=pick(args, env, "log_level", "INFO"), map_rate_hz=args.map_rate,
                        update_rate_hz=args.update_rate, lag_s=args.lag)

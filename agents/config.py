"""The agent process's one frozen config."""

from __future__ import annotations

import argparse
from collections.abc import Mapping, Sequence

import msgspec

from tagswarm.agents.controller import load_factory
from tagswarm.protocol.bus import BusConfig
from tagswarm.protocol.scenario import Scenario
from tagswarm.runtime.config import ConfigError, Invocation, OneLineParser, add_common_args


class AgentConfig(msgspec.Struct, frozen=True, kw_only=True):
    """Everything one agent needs; built once in ``main``."""

    scenario: Scenario
    bus: BusConfig
    robot_id: int
    run: str = "default"
    log_level: str = "INFO"
    fetch_map_timeout_s: float = 1.0
    inject_frame_delay_s: float = 0.0  # extra seconds per processed frame (overload tests); agent.inject_frame_delay_s
    agent_module: str | None = None  # a user's controller (tagswarm.agents.controller); None = built-in behaviour

    @property
    def participant(self) -> str:
        return f"agent/{self.robot_id}"


def parser(prog: str = "tagswarm-agent") -> argparse.ArgumentParser:
    p = OneLineParser(
        prog=prog,
        description="A tagswarm robot agent: detects the tag cubes of other robots in its camera images, estimates "
        "their relative poses, dead-reckons from its wheel encoders, follows its mission and re-localises "
        "actively (rotates in place) when it has been on odometry alone for too long.")
    add_common_args(p)
    p.add_argument("--robot-id", type=int, help="which robot this agent drives (env TAGSWARM_ROBOT_ID); required")
    p.add_argument("--fetch-map-timeout", type=float, default=1.0, metavar="SECONDS",
                   help="how long to ask the server for this robot's last pose at start (default 1; 0 = skip)")
    p.add_argument("--inject-frame-delay", type=float, metavar="SECONDS",
                   help="fault injection: spend this much extra wall time on every camera frame, as a slow detector "
                        "would (frames are then skipped, never queued); same as --set agent.inject_frame_delay_s=S")
    p.add_argument("--agent-module", metavar="MODULE",
                   help="drive this robot with your own controller instead of the built-in behaviour: a module "
                        "importable in this process (pkg.mod, see PYTHONPATH) or a path to a .py file, defining "
                        "make_controller(config) -> tagswarm.agents.controller.Controller; detection, odometry and "
                        "localisation stay as they are (env TAGSWARM_AGENT_MODULE; see docs/controllers.md)")
    return p


def build_config(argv: Sequence[str] | None = None, environ: Mapping[str, str] | None = None) -> AgentConfig:
    inv = Invocation(parser(), argv, environ)
    args = inv.args
    if args.inject_frame_delay is not None:
        if not args.inject_frame_delay >= 0:  # also NaN
            raise ConfigError("--inject-frame-delay must be >= 0 seconds")
        args.overrides.append(f"agent.inject_frame_delay_s={args.inject_frame_delay!r}")
    scenario = inv.scenario()
    raw = inv.pick("robot_id")
    if raw is None:
        raise ConfigError("--robot-id is required (or TAGSWARM_ROBOT_ID)")
    try:
        robot_id = int(raw)
    except ValueError:
        raise ConfigError(f"--robot-id must be an integer, got {raw!r}") from None
    if robot_id not in scenario.robot_ids:
        raise ConfigError(f"--robot-id {robot_id} is not a robot of scenario {scenario.name!r} "
                          f"(0..{scenario.robots.count - 1})")
    run = inv.run()
    if args.fetch_map_timeout < 0:
        raise ConfigError("--fetch-map-timeout must be >= 0")
    agent_module = inv.pick("agent_module") or None
    if agent_module is not None:
        load_factory(agent_module)  # import now: a broken module is a one-line error (exit 2) at start
    return AgentConfig(scenario=scenario, bus=inv.bus(), robot_id=robot_id, run=run,
                       log_level=inv.log_level(), fetch_map_timeout_s=args.fetch_map_timeout,
                       inject_frame_delay_s=scenario.agent.inject_frame_delay_s, agent_module=agent_module)

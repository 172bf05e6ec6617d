"""``tagswarm``: one entry point for every role and tool.

``tagswarm world ...`` runs exactly what ``tagswarm-world ...`` runs (compose uses
the console scripts; people use the subcommands).
"""

from __future__ import annotations

import importlib
import sys
from collections.abc import Callable, Sequence

from tagswarm.protocol.scenario import builtin_descriptions

# name -> (help, module, function); modules are imported only when their command
# runs, so `tagswarm alive` (a compose healthcheck) does not load pybullet or GTSAM
COMMANDS: dict[str, tuple[str, str, str]] = {
    "up": ("run a whole swarm (world, server, agents) and write a run folder with metrics and plots",
           "tagswarm.up", "main"),
    "report": ("evaluate a run folder again: metrics.json + plots", "tagswarm.evaluation.report", "main"),
    "snapshot": ("start a world, grab one frame per camera, decode tags, write PNGs + JSON", "tagswarm.view.snapshot",
                 "main"),
    "world": ("run the world process (physics, cameras, encoders, clock)", "tagswarm.world.node", "main"),
    "render": ("run one render worker for a world started with --no-spawn-workers",
               "tagswarm.world.render_worker", "main"),
    "agent": ("run one robot's agent (detection, cube pose, odometry, behaviour)", "tagswarm.agents.node", "main"),
    "server": ("run the map server (stitching, pose-graph fusion, corrections)", "tagswarm.server.node", "main"),
    "router": ("run a Zenoh router for client-mode processes (compose), with a heartbeat file",
               "tagswarm.deploy.router", "main"),
    "spy": ("live table of a running system's keys: types, rates, bandwidth, last message", "tagswarm.spy.spy",
            "main"),
    "goto": ("send a robot to (X, Y) in the map frame once its agent is alive", "tagswarm.operator.goto", "main"),
    "kidnap": ("teleport (or --push) a robot to (X, Y) in the arena frame; its odometry does not see it",
               "tagswarm.operator.kidnap", "main"),
    "alive": ("exit 0 if a participant's liveliness token is visible, else 1 (healthchecks)", "tagswarm.deploy.alive",
              "main"),
    "claim": ("claim a free robot id from the run's claim authority, then run a command as that robot's agent",
              "tagswarm.deploy.claim", "main"),
    "record-run": ("record a run started by others (compose) and write its run folder with metrics and plots",
                   "tagswarm.deploy.recordrun", "main"),
    "record": ("record every message on matching keys to an MCAP file (opens in Foxglove)",
               "tagswarm.recording.record", "main"),
    "replay": ("republish an MCAP recording on Zenoh (1x, a chosen speed, or lockstep)",
               "tagswarm.recording.replay", "main"),
    "view": ("serve a live web view of the arena (robots, map, cameras) on 127.0.0.1", "tagswarm.view.view", "main"),
}


def _entry(name: str) -> Callable[[Sequence[str] | None], int]:
    _, module, func = COMMANDS[name]
    fn: Callable[[Sequence[str] | None], int] = getattr(importlib.import_module(module), func)
    return fn


USAGE = """usage: tagswarm COMMAND [ARGS...]

tagswarm simulates a swarm of ground robots that localise each other by reading
AprilTag cubes, over Zenoh.  Each command has its own --help.

commands:
{commands}
  scenarios  list the built-in scenarios
"""


def main(argv: Sequence[str] | None = None) -> int:
    """Console script ``tagswarm``."""
    args = list(sys.argv[1:] if argv is None else argv)
    listing = "\n".join(f"  {name:<10} {text}" for name, (text, _, _) in COMMANDS.items())
    if not args or args[0] in ("-h", "--help"):
        print(USAGE.format(commands=listing))
        return 0
    name, rest = args[0], args[1:]
    if name == "scenarios":
        if rest and rest[0] in ("-h", "--help"):
            print("usage: tagswarm scenarios\n\nList the built-in scenarios, one line each: pass a name to "
                  "--scenario (tagswarm up --scenario hall), or a path to your own TOML file (README, "
                  "'Your own scene').")
            return 0
        if rest:
            from tagswarm.runtime.config import ConfigError
            from tagswarm.runtime.process import run_main

            def extra() -> int:
                raise ConfigError(f"scenarios takes no arguments, got {' '.join(rest)!r}")

            return run_main("tagswarm scenarios", extra)
        described = builtin_descriptions()
        width = max(map(len, described), default=0)
        print("\n".join(f"{n:<{width}}  {d}" for n, d in described.items()))
        return 0
    if name not in COMMANDS:
        from tagswarm.runtime.config import ConfigError  # here: the other paths need not load Zenoh
        from tagswarm.runtime.process import run_main

        def unknown() -> int:
            raise ConfigError(f"unknown command {name!r} (commands: {', '.join(COMMANDS)}, scenarios)")

        return run_main("tagswarm", unknown)
    return _entry(name)(rest)


if __name__ == "__main__":
    raise SystemExit(main())

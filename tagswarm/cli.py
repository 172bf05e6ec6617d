"""``tagswarm``: one entry point for every role and tool.

``tagswarm world ...`` runs exactly what ``tagswarm-world ...`` runs (compose uses
the console scripts; people use the subcommands).
"""

from __future__ import annotations

import sys
from collections.abc import Callable, Sequence

from protocol.scenario import builtin_names


def _commands() -> dict[str, tuple[str, Callable[[Sequence[str] | None], int]]]:
    from agents import node as agent_node
    from server import node as server_node
    from tagswarm import report, snapshot, up
    from world import node as world_node
    from world import render_worker

    return {
        "up": ("run a whole swarm (world, server, agents) and write a run folder with metrics and plots", up.main),
        "report": ("evaluate a run folder again: metrics.json + plots", report.main),
        "snapshot": ("start a world, grab one frame per camera, decode tags, write PNGs + JSON", snapshot.main),
        "world": ("run the world process (physics, cameras, encoders, clock)", world_node.main),
        "render": ("run one render worker for a world started with --no-spawn-workers", render_worker.main),
        "agent": ("run one robot's agent (detection, cube pose, odometry, behaviour)", agent_node.main),
        "server": ("run the map server (stitching, pose-graph fusion, corrections)", server_node.main),
    }


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
    commands = _commands()
    listing = "\n".join(f"  {name:<10} {text}" for name, (text, _) in commands.items())
    if not args or args[0] in ("-h", "--help"):
        print(USAGE.format(commands=listing))
        return 0
    name, rest = args[0], args[1:]
    if name == "scenarios":
        print("\n".join(builtin_names()))
        return 0
    if name not in commands:
        sys.stderr.write(f"tagswarm: error: unknown command {name!r} (commands: {', '.join(commands)}, scenarios)\n")
        return 2
    return commands[name][1](rest)


if __name__ == "__main__":
    raise SystemExit(main())

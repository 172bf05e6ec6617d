"""``tagswarm kidnap ROBOT X Y``: teleport (or push) a robot in the running world.

Moves robot ROBOT's base to (X, Y) metres in the *arena* frame (the simulated
world's frame: origin at the arena centre, x and y along the walls, z up; not
the map frame of ``tagswarm goto``, which is the origin robot's start pose),
facing ``--yaw`` radians (counter-clockwise from +x, default 0).  With
``--push`` X, Y and ``--yaw`` are an offset from the robot's current pose
instead, still along the arena axes.  The robot's wheels do not turn, so its
encoders and odometry do not see the move: a kidnapped robot.

Joins the network with the same flags and ``TAGSWARM_*`` variables as every
process, waits (up to ``--timeout``) until the world's liveliness token
``tagswarm/<run>/alive/world/0`` is visible (the world subscribes before it
declares it) and, within the same ``--timeout``, until this session knows a
subscriber of ``tagswarm/<run>/world/command`` (Zenoh matching status: a put
before that would be lost), publishes one
:class:`tagswarm.protocol.messages.WorldCommand` there and exits 0.  The world applies it at the
first step whose simulation time is >= ``--at`` seconds (default: its next
step).  ``--at`` is rounded up to a whole world tick, so a lockstep run with the
same ``--at`` is repeatable: the tick length comes from the world's next tick,
or, if none comes within half a second (a lockstep world waiting for a
participant), from ``clock.tick_hz`` of the scenario given here (``--scenario``,
``--set``; default ``paper``).  The
world refuses (and counts as ``world_command_rejected`` in its status, with a
log line) a robot it does not have, a pose outside the arena walls or
overlapping a wall, obstacle or another robot.  Without ``--at`` this command
then waits (up to :data:`~tagswarm.operator.reach.CONFIRM_S`) for the world's status to show whether it
applied or refused it, and says which.  Exit 1 (one line) when the world is not
alive or refused the command; exit 2 (one line) for bad arguments or when nobody
subscribes to the command key within ``--timeout``.
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from collections.abc import Mapping, Sequence

from tagswarm.operator.reach import (
    CONFIRM_S,
    MAX_ROBOT_ID,
    TICK_WAIT_S,
    newest_counters,
    next_tick,
    outcome,
    publish_once,
    wait_alive,
)
from tagswarm.protocol import codec
from tagswarm.protocol import messages as m
from tagswarm.protocol.bus import open_bus
from tagswarm.protocol.keys import Keys
from tagswarm.runtime.config import (
    ConfigError,
    Invocation,
    OneLineParser,
    add_common_args,
)
from tagswarm.runtime.process import run_main, setup_logging

PROG = "tagswarm kidnap"


def parser() -> OneLineParser:
    p = OneLineParser(prog=PROG, description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("robot", type=int, metavar="ROBOT", help="robot id")
    p.add_argument("x", type=float, metavar="X", help="x in the arena frame (m); with --push, the offset along x")
    p.add_argument("y", type=float, metavar="Y", help="y in the arena frame (m); with --push, the offset along y")
    p.add_argument("--yaw", type=float, default=0.0, metavar="RAD",
                   help="heading in the arena frame (rad, counter-clockwise from +x; default 0); "
                   "with --push, the turn")
    p.add_argument("--push", action="store_true", help="move by (X, Y, --yaw) from the current pose")
    p.add_argument("--at", type=float, default=None, metavar="SECONDS",
                   help="simulation time to apply it at (default: the world's next step)")
    p.add_argument("--timeout", type=float, default=10.0, metavar="SECONDS",
                   help="how long to wait for the world's liveliness token and a subscriber of the command "
                   "key, in all (default 10)")
    add_common_args(p, scenario="file", faults=False)
    return p


def make_command(robot: int, x: float, y: float, yaw: float, push: bool, stamp_ns: int = 0) -> m.WorldCommand:
    """The WorldCommand; raises ConfigError (one line) for values the wire would reject."""
    if not 0 <= robot <= MAX_ROBOT_ID:
        raise ConfigError(f"ROBOT must be between 0 and {MAX_ROBOT_ID}, got {robot}")
    if not (math.isfinite(x) and math.isfinite(y)):
        raise ConfigError(f"X and Y must be finite numbers (metres), got {x!r}, {y!r}")
    if not math.isfinite(yaw):
        raise ConfigError(f"--yaw must be a finite number of radians, got {yaw!r}")
    return m.WorldCommand(seq=0, stamp_ns=stamp_ns, robot_id=robot, action="push" if push else "teleport",
                          x_m=x, y_m=y, yaw_rad=yaw)


def refusal(robot: int, counters: Mapping[str, int]) -> str:
    """Why the world most likely refused a command for ``robot`` (one line; its log says exactly)."""
    roster = sorted(int(k.rsplit("_", 1)[1]) for k in counters
                    if k.startswith("contacts_robot_") and k.rsplit("_", 1)[1].isdigit())
    if roster and robot not in roster:
        return f"robot {robot} is not in the world's roster (robots {', '.join(map(str, roster))})"
    return ("the pose is outside the arena walls or overlaps a wall, obstacle or another robot "
            "(the world's log says which)")


def stamp_for(at_s: float, dt_ns: int | None) -> int:
    """``at_s`` seconds as a stamp: ``k * dt_ns`` (a tick's stamp) for the first tick ``k``
    at or after ``at_s`` when the tick length ``dt_ns`` is known, else nanoseconds.
    Within a thousandth of a tick counts as on it: ``dt_ns`` is rounded (33333333 at
    30 Hz), so 1 s is tick 30 although its stamp is 0.99999999 s."""
    if dt_ns is None:
        return math.ceil(at_s * 1e9)
    ticks = at_s * 1e9 / dt_ns
    k = round(ticks) if abs(ticks - round(ticks)) < 1e-3 else math.ceil(ticks)
    return k * dt_ns


def main(argv: Sequence[str] | None = None) -> int:
    """Console entry for ``tagswarm kidnap``: 0 sent (and applied, when confirmed), 1 world not alive or
    command refused, 2 bad arguments."""

    def body() -> int:
        inv = Invocation(parser(), argv)
        args = inv.args
        make_command(args.robot, args.x, args.y, args.yaw, args.push)  # validate before touching the network
        if args.at is not None and (not math.isfinite(args.at) or args.at < 0):
            raise ConfigError(f"--at must be a simulation time in seconds >= 0, got {args.at!r}")
        if not math.isfinite(args.timeout) or args.timeout <= 0:
            raise ConfigError("--timeout must be a positive number of seconds")
        setup_logging(inv.log_level("WARNING"), "kidnap")  # validates --log-level too
        run = inv.pick("run", "default")
        keys = Keys(run)
        # the scenario's tick length stands in when the world sends no tick (so also validated up front)
        scenario_dt_ns = round(1e9 / inv.scenario().clock.tick_hz) if args.at is not None else None
        alive_key = keys.alive("world/0")
        with open_bus(inv.bus()) as bus:
            deadline = time.monotonic() + args.timeout
            if not wait_alive(bus, alive_key, args.timeout):
                sys.stderr.write(f"{PROG}: error: the world is not alive on run {run!r} "
                                 f"(no liveliness token {alive_key} after {args.timeout:g} s)\n")
                return 1
            stamp = 0
            if args.at is not None:
                tick = next_tick(bus, keys, TICK_WAIT_S)
                stamp = stamp_for(args.at, (tick.dt_ns if tick is not None else None) or scenario_dt_ns)
            cmd = make_command(args.robot, args.x, args.y, args.yaw, args.push, stamp)
            statuses = bus.subscribe(keys.world_status(), newest_only=True) if args.at is None else None
            before = None if statuses is None else newest_counters(statuses, bus, CONFIRM_S / 2)
            publish_once(bus, keys.world_command(), codec.encode(cmd), max(0.0, deadline - time.monotonic()))
            # a round trip on the same link before closing the session, so the command is on its way
            bus.alive_now(alive_key, 1.0)
            verdict, after = None, None
            if statuses is not None and before is not None:
                until = time.monotonic() + CONFIRM_S
                while verdict is None and time.monotonic() < until:
                    after = newest_counters(statuses, bus, until - time.monotonic())
                    verdict = None if after is None else outcome(before, after, "world_commands",
                                                                 "world_command_rejected")
        when = "at the world's next step" if stamp == 0 else f"at t={stamp / 1e9:.3f} s"
        what = "by" if args.push else "to"
        done = f"{cmd.action} robot {cmd.robot_id} {what} ({cmd.x_m:.3f} m, {cmd.y_m:.3f} m, {cmd.yaw_rad:.3f} rad)"
        if verdict == "refused":
            assert after is not None
            sys.stderr.write(f"{PROG}: error: the world refused the {done}: {refusal(cmd.robot_id, after)}\n")
            return 1
        confirmed = {"applied": ": applied by the world",
                     None: "" if args.at is not None else " (the world's status did not confirm it within "
                                                           f"{CONFIRM_S:g} s)"}[verdict]
        print(f"{done} in the arena frame sent on {keys.world_command()}, {when}{confirmed}")
        return 0

    return run_main(PROG, body)


if __name__ == "__main__":
    raise SystemExit(main())

"""``tagswarm goto ROBOT X Y``: send a robot to (X, Y) in the map frame.

Joins the network with the same flags and ``TAGSWARM_*`` variables as every
process, waits (up to ``--timeout``) until the agent's liveliness token
``tagswarm/<run>/alive/agent/ROBOT`` is visible, so that its goal subscriber is
known (agents subscribe before they declare the token), then, within the same
``--timeout``, until this session knows a subscriber of
``tagswarm/<run>/robot/ROBOT/goal`` (Zenoh matching status: a put before that
would be lost), publishes one :class:`tagswarm.protocol.messages.Goal` there
(exit 0).  The goal is stamped with the simulation time of the newest world
tick, if the world is ticking.  It then waits (up to
:data:`~tagswarm.operator.reach.CONFIRM_S`) for the agent's status to show the goal taken, or
refused (a robot could not stand there: beyond the walls or on an obstacle).  Exit 1 (one line)
when the agent is not alive or refused the goal;
exit 2 (one line) for bad arguments, e.g. a non-finite X or Y, or when nobody
subscribes to the goal key within ``--timeout``.
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from collections.abc import Sequence

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
from tagswarm.runtime.config import ConfigError, Invocation, OneLineParser, add_common_args
from tagswarm.runtime.process import run_main, setup_logging

PROG = "tagswarm goto"


def parser() -> OneLineParser:
    p = OneLineParser(prog=PROG, description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("robot", type=int, metavar="ROBOT", help="robot id")
    p.add_argument("x", type=float, metavar="X", help="goal x in the map frame (m)")
    p.add_argument("y", type=float, metavar="Y", help="goal y in the map frame (m)")
    p.add_argument("--tolerance", type=float, default=0.1, metavar="M",
                   help="the robot stops within this distance of the goal (default 0.1)")
    p.add_argument("--timeout", type=float, default=10.0, metavar="SECONDS",
                   help="how long to wait for the agent's liveliness token and a subscriber of the goal key, "
                   "in all (default 10)")
    add_common_args(p, scenario="none", faults=False)
    return p


def make_goal(robot: int, x: float, y: float, tolerance: float, stamp_ns: int = 0) -> m.Goal:
    """The Goal message; raises ConfigError (one line) for values the wire would reject."""
    if not 0 <= robot <= MAX_ROBOT_ID:
        raise ConfigError(f"ROBOT must be between 0 and {MAX_ROBOT_ID}, got {robot}")
    if not (math.isfinite(x) and math.isfinite(y)):
        raise ConfigError(f"X and Y must be finite numbers (metres), got {x!r}, {y!r}")
    if not math.isfinite(tolerance) or tolerance <= 0:
        raise ConfigError(f"--tolerance must be a positive number of metres, got {tolerance!r}")
    return m.Goal(seq=0, stamp_ns=stamp_ns, robot_id=robot, x_m=x, y_m=y, tolerance_m=tolerance)


def main(argv: Sequence[str] | None = None) -> int:
    """Console entry for ``tagswarm goto``: 0 sent (and taken, when confirmed), 1 agent not alive or goal
    refused, 2 bad arguments."""

    def body() -> int:
        inv = Invocation(parser(), argv)
        args = inv.args
        make_goal(args.robot, args.x, args.y, args.tolerance)  # validate before touching the network
        if not math.isfinite(args.timeout) or args.timeout <= 0:
            raise ConfigError("--timeout must be a positive number of seconds")
        setup_logging(inv.log_level("WARNING"), "goto")  # validates --log-level too
        run = inv.pick("run", "default")
        keys = Keys(run)
        participant = f"agent/{args.robot}"
        alive_key = keys.alive(participant)
        with open_bus(inv.bus()) as bus:
            deadline = time.monotonic() + args.timeout
            if not wait_alive(bus, alive_key, args.timeout):
                sys.stderr.write(f"{PROG}: error: {participant} is not alive on run {run!r} "
                                 f"(no liveliness token {alive_key} after {args.timeout:g} s)\n")
                return 1
            tick = next_tick(bus, keys, TICK_WAIT_S, lambda t: t.stamp_ns > 0)  # stamped like the world's time
            goal = make_goal(args.robot, args.x, args.y, args.tolerance, tick.stamp_ns if tick is not None else 0)
            statuses = bus.subscribe(keys.robot_status(args.robot), newest_only=True)
            before = newest_counters(statuses, bus, CONFIRM_S / 2)
            publish_once(bus, keys.goal(args.robot), codec.encode(goal), max(0.0, deadline - time.monotonic()))
            # a round trip on the same link before closing the session, so the goal is on its way
            bus.alive_now(alive_key, 1.0)
            verdict, until = None, time.monotonic() + CONFIRM_S
            while before is not None and verdict is None and time.monotonic() < until:
                after = newest_counters(statuses, bus, until - time.monotonic())
                verdict = None if after is None else outcome(before, after, "goals", "goals_refused")
        sent = f"goal ({goal.x_m:.2f}, {goal.y_m:.2f}) ±{goal.tolerance_m:g} m"
        if verdict == "refused":
            sys.stderr.write(f"{PROG}: error: {participant} refused the {sent} in the map frame: a robot cannot stand "
                             "there (beyond the arena walls or on an obstacle; the agent's log says which)\n")
            return 1
        confirmed = {"applied": ", taken by the agent",
                     None: f" (the agent's status did not confirm it within {CONFIRM_S:g} s)"}[verdict]
        print(f"{sent} sent to {participant} on {keys.goal(args.robot)} at t={goal.stamp_ns / 1e9:.2f} s{confirmed}")
        return 0

    return run_main(PROG, body)


if __name__ == "__main__":
    raise SystemExit(main())

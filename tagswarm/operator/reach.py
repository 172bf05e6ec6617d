"""Reaching a running system from an operator command: wait for a participant's liveliness
token, read the next world tick (the simulation time and tick length a command is stamped
with).  Undecodable ticks are skipped, never raised."""

from __future__ import annotations

from collections.abc import Callable

from tagswarm.protocol import codec
from tagswarm.protocol import messages as m
from tagswarm.protocol.bus import Bus
from tagswarm.protocol.keys import Keys

MAX_ROBOT_ID = 100_000  # tagswarm.protocol.messages.RobotId
#: how long a command waits for a tick of a running world before it goes without one (wall seconds)
TICK_WAIT_S = 0.5


def wait_alive(bus: Bus, key: str, timeout_s: float) -> bool:
    """True once a liveliness token on ``key`` is (or already was) visible."""
    changes = bus.watch_liveliness(key)
    seen = False

    def up() -> bool:
        nonlocal seen
        seen = seen or any(c.value for c in changes.drain())
        return seen

    return bus.wait_for(up, timeout_s)


def next_tick(bus: Bus, keys: Keys, timeout_s: float,
              accept: Callable[[m.Tick], bool] = lambda tick: True) -> m.Tick | None:
    """The next world tick that ``accept`` takes, or None if none comes within ``timeout_s``."""
    ticks = bus.subscribe(keys.tick(), newest_only=True)
    found: m.Tick | None = None

    def got() -> bool:
        nonlocal found
        for item in ticks.drain():
            try:
                tick = codec.decode(m.Tick, item.value)
            except codec.DecodeError:
                continue
            if accept(tick) and (found is None or tick.stamp_ns >= found.stamp_ns):
                found = tick
        return found is not None

    bus.wait_for(got, timeout_s)
    return found

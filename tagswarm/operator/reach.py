"""Reaching a running system from an operator command: wait for a participant's liveliness
token, read the next world tick (the simulation time and tick length a command is stamped
with), wait until the command's key has a subscriber, publish once.  Undecodable ticks are
skipped, never raised.

Why wait for a subscriber: a command publishes one message and exits.  A Zenoh put goes
only to the subscribers this session already knows of, and a subscription is learnt
asynchronously after the session opens (and after the liveliness token the command waited
for: another process, such as a recorder that joined a moment ago, may subscribe through a
link that is still being set up).  A put before that is silently lost.  The publisher's
*matching status* (Zenoh 1.x) says when the session knows at least one matching
subscriber, so :func:`publish_once` waits for it and publishes (BLOCK, express: the sample
is handed to the link at once); the command then makes one liveliness round trip and
leaves ``open_bus`` to close the session cleanly, never exiting with it open.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping

from tagswarm.protocol import codec
from tagswarm.protocol import messages as m
from tagswarm.protocol.bus import Bus, Inbox
from tagswarm.protocol.errors import UsageError
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


#: how long a command waits for its receiver's status to confirm it (a status comes every second of simulated
#: time: a baseline before the command, then the one that counts it)
CONFIRM_S = 5.0


def newest_counters(inbox: Inbox[bytes], bus: Bus, timeout_s: float) -> dict[str, int] | None:
    """The counters of the newest status in ``inbox`` (waiting up to ``timeout_s`` for one), else None."""
    found: list[dict[str, int]] = []

    def got() -> bool:
        for item in inbox.drain():
            try:
                found.append(dict(codec.decode(m.AgentStatus, item.value).counters))
            except codec.DecodeError:
                continue
        return bool(found)

    bus.wait_for(got, timeout_s)
    return found[-1] if found else None


def outcome(before: Mapping[str, int], after: Mapping[str, int], applied: str, refused: str) -> str | None:
    """``"refused"`` or ``"applied"`` once status counters ``after`` count one more in ``refused`` or
    ``applied`` than ``before`` did, else None."""
    if after.get(refused, 0) > before.get(refused, 0):
        return "refused"
    if after.get(applied, 0) > before.get(applied, 0):
        return "applied"
    return None


class NoSubscriberError(UsageError):
    """Nobody subscribes to a command's key: exit 2, one line."""


def publish_once(bus: Bus, key: str, payload: bytes, timeout_s: float) -> None:
    """Publish ``payload`` on ``key`` once a subscriber is known (see the module docstring);
    :class:`NoSubscriberError` if none is within ``timeout_s`` wall seconds."""
    if not bus.wait_matched(key, timeout_s):
        raise NoSubscriberError(f"nobody subscribes to {key} (waited {timeout_s:.1f} s): "
                                "is the process that reads it running on this run and network?")
    bus.put(key, payload)

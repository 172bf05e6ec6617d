"""Robot-id claims: how identical agent containers (``docker compose up --scale agent=N``)
each get a robot of their own, with that robot's credentials.

An agent container starts knowing only the ``claimant`` login (the same for every
replica; the router lets it do nothing but ask for an id and watch presence).  It
queries the claim key (``Keys.claim()``); the claim authority (the compose run's
recorder, ``tagswarm record-run --claims FILE``) answers with the lowest robot id not
handed out yet and that robot's Zenoh user and password (``agent<k>``, from
``agents.txt`` written by ``tagswarm router --make-secrets``), so the agent then logs in
as ``agent<k>`` and the router's ACL confines it to robot k's keys.  Each id is handed
out once per run; when none is left the reply says so (``tagswarm claim`` exits 2).

:class:`ClaimBook` is the authority's bookkeeping (pure); the reply's payload is the
protocol message :class:`~tagswarm.protocol.messages.ClaimReply`.  The trade-off (the
authority holds every agent's password; the password travels in a Zenoh reply, in clear
over plain TCP) is in docs/security.md.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path

from tagswarm.deploy import acl
from tagswarm.protocol import codec
from tagswarm.protocol import messages as m
from tagswarm.runtime.config import ConfigError

ClaimReply = m.ClaimReply  # the reply's payload: a protocol message


def encode(reply: ClaimReply) -> bytes:
    """The reply as wire bytes."""
    return codec.encode(reply)


def decode(payload: bytes) -> ClaimReply | None:
    """A reply, or None when ``payload`` is not one (dropped by the caller)."""
    try:
        return codec.decode(m.ClaimReply, payload)
    except codec.DecodeError:
        return None


def read_passwords(path: Path) -> dict[str, str]:
    """``user:password`` lines (``agents.txt``) -> {user: password}."""
    try:
        text = path.read_text()
    except OSError as exc:
        raise ConfigError(f"--claims: cannot read {str(path)!r}: {exc.strerror}") from None
    out = {}
    for n, line in enumerate(text.splitlines(), 1):
        if not line.strip():
            continue
        user, sep, password = line.strip().partition(":")
        if not sep or not user or not password:
            raise ConfigError(f"--claims: {str(path)!r} line {n} is not user:password")
        out[user] = password
    return out


class ClaimBook:
    """Which robot ids have been handed out; ids go lowest first, each once."""

    def __init__(self, robot_ids: Sequence[int], passwords: Mapping[str, str]) -> None:
        self.robot_ids = tuple(robot_ids)
        self.passwords = dict(passwords)
        missing = [acl.agent_user(r) for r in self.robot_ids if acl.agent_user(r) not in self.passwords]
        if missing:
            raise ConfigError(f"--claims: no password for {', '.join(missing)} (run tagswarm router "
                              f"--make-secrets DIR --robots {len(self.robot_ids)})")
        self.taken: list[int] = []
        self.refused = 0

    def claim(self) -> ClaimReply:
        """Hand out the next free robot id, or refuse when every one is taken."""
        free = [r for r in self.robot_ids if r not in self.taken]
        if not free:
            self.refused += 1
            return ClaimReply(seq=len(self.taken) + self.refused, stamp_ns=0, robot_id=-1, robots=len(self.robot_ids),
                              reason=f"every robot id is taken ({len(self.robot_ids)} robots)")
        rid = free[0]
        self.taken.append(rid)
        user = acl.agent_user(rid)
        return ClaimReply(seq=len(self.taken) + self.refused, stamp_ns=0, robot_id=rid, robots=len(self.robot_ids),
                          user=user, password=self.passwords[user])

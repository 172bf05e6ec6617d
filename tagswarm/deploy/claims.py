"""Robot-id claims: how identical agent containers (``docker compose up --scale agent=N``)
each get a robot of their own, with that robot's credentials.

An agent container starts knowing only the ``claimant`` login (the same for every
replica; the router lets it do nothing but ask for an id and watch presence).  It
queries :func:`tagswarm.deploy.acl.claim_key`; the claim authority (the compose run's
recorder, ``tagswarm record-run --claims FILE``) answers with the lowest robot id not
handed out yet and that robot's Zenoh user and password (``agent<k>``, from
``agents.txt`` written by ``tagswarm router --make-secrets``), so the agent then logs in
as ``agent<k>`` and the router's ACL confines it to robot k's keys.  Each id is handed
out once per run; when none is left the reply says so (``tagswarm claim`` exits 2).

:class:`ClaimBook` is the authority's bookkeeping (pure); :class:`ClaimReply` the
reply's payload.  The trade-off (the authority holds every agent's password; the
password travels in a Zenoh reply, in clear over plain TCP) is in docs/security.md.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path

import msgspec

from tagswarm.deploy import acl
from tagswarm.runtime.config import ConfigError


class ClaimReply(msgspec.Struct, frozen=True, kw_only=True, forbid_unknown_fields=True):
    """The claim authority's answer: a robot id (0..) with its Zenoh login, or
    ``robot_id`` -1 and the reason.  ``robots`` is the run's number of robots."""

    # TODO(protocol/messages.py owner): a protocol message once claims are part of the protocol
    robot_id: int
    robots: int
    user: str = ""
    password: str = ""
    reason: str = ""

    @property
    def granted(self) -> bool:
        return self.robot_id >= 0


def encode(reply: ClaimReply) -> bytes:
    """The reply as msgpack bytes."""
    return msgspec.msgpack.encode(reply)


def decode(payload: bytes) -> ClaimReply | None:
    """A reply, or None when ``payload`` is not one (dropped by the caller)."""
    try:
        return msgspec.msgpack.decode(payload, type=ClaimReply)
    except (msgspec.DecodeError, msgspec.ValidationError):
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
            return ClaimReply(robot_id=-1, robots=len(self.robot_ids),
                              reason=f"every robot id is taken ({len(self.robot_ids)} robots)")
        rid = free[0]
        self.taken.append(rid)
        user = acl.agent_user(rid)
        return ClaimReply(robot_id=rid, robots=len(self.robot_ids), user=user, password=self.passwords[user])

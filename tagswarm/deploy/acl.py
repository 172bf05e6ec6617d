"""Zenoh access control for a tagswarm deployment, generated from the key layout.

Every process is a Zenoh client of one router and logs in with its role's user
name (Zenoh user/password authentication); the router's ACL, built here from
:class:`tagswarm.protocol.keys.Keys` so it cannot drift from the keys the nodes use,
allows each user exactly what its process does and denies everything else:

============  =====================================================================
user          may
============  =====================================================================
world         publish the clock, world status, render requests and every robot's
              sensors (camera images, encoders) and ground truth; receive wheel
              commands, world commands (teleport / push), tick acks, render
              requests (its render workers log in as world too: they publish
              images and acks ``render/<i>``)
agent<k>      publish robot k's observation, odometry, status, wheel command and
              the ack ``agent/<k>``; receive robot k's images, encoders,
              correction, goal, the clock and the map (collision avoidance); query the map
server        publish the map, its status, every robot's correction and the ack
              ``server/0``; receive observations, odometry, the clock and the
              agents' acks ``agent/<k>`` (lockstep: an ack without its odometry
              tells the server that odometry was lost); answer map queries
viewer        receive everything of the run, query the map (spy, recorder, alive)
operator      what viewer may, plus publish goals (``tagswarm goto``) and world
              commands (``tagswarm kidnap``)
recorder      what viewer may, plus answer robot-id claims (``tagswarm record-run``,
              the compose run's recorder and claim authority) and declare its token
claimant      ask for a robot id (``tagswarm claim``, before an agent starts) and
              watch presence (its container's healthcheck); nothing else
============  =====================================================================

Everyone may watch presence (liveliness) under ``alive/``; each process may
declare only its own liveliness token.  In Zenoh's terms (messages seen by the
router): *ingress* is what a client sends, *egress* what the router forwards to it.

Everyone also receives the *declarations* of subscribers and queryables of the
run (``discover``): they carry no data, but a Zenoh publisher sends nothing once
it has learnt that no subscriber matches its key (write-side filtering), so a
publisher that is denied them goes silent after its first message.  The router
matches an egress declaration against the rule by inclusion, and subscribers such
as the server's ``robot/*/observation`` or a viewer's ``**`` are wildcards, hence
the whole run rather than each role's own keys.
"""

from __future__ import annotations

import dataclasses
import json
import os
import re
import secrets
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, fields
from pathlib import Path
from typing import Any

from tagswarm.protocol.keys import Keys

WORLD, SERVER, VIEWER, OPERATOR = "world", "server", "viewer", "operator"
RECORDER, CLAIMANT = "recorder", "claimant"
#: the recorder's liveliness token (a lockstep observer: the world waits for it before the first tick)
RECORDER_PARTICIPANT = "recorder/0"
#: the file name of Zenoh's ``user:password`` dictionary written by :func:`make_secrets`
USERS_FILE = "users.txt"
#: the agents' part of it, for the claim authority (tagswarm/deploy/claims.py)
AGENTS_FILE = "agents.txt"
PASSWORD_SUFFIX = ".password"


#: an agent's user name: ``agent<k>``
AGENT_USER = re.compile(r"agent(0|[1-9][0-9]*)")


def agent_user(robot_id: int) -> str:
    """The Zenoh user name of robot ``robot_id``'s agent."""
    return f"agent{int(robot_id)}"


def users(robot_ids: Iterable[int]) -> list[str]:
    """Every user of a deployment with these robots, in a stable order."""
    return [WORLD, SERVER, *(agent_user(r) for r in robot_ids), VIEWER, OPERATOR, RECORDER, CLAIMANT]


def claim_key(keys: Keys) -> str:
    """Where agents ask for a robot id (:meth:`Keys.claim`; a query whose reply carries the
    id and that robot's credentials)."""
    return keys.claim()


@dataclass(frozen=True)
class Grant:
    """What one user may do, as key expressions per kind of operation."""

    put: tuple[str, ...] = ()  # publish
    sub: tuple[str, ...] = ()  # subscribe, and so receive publications
    serve: tuple[str, ...] = ()  # declare a queryable, receive queries, reply
    ask: tuple[str, ...] = ()  # send queries, receive replies
    token: tuple[str, ...] = ()  # declare liveliness tokens
    watch: tuple[str, ...] = ()  # liveliness subscribers and queries, receive tokens
    discover: tuple[str, ...] = ()  # receive subscriber and queryable declarations (no data)


#: operation -> ((flow, Zenoh ACL messages), ...)
_MESSAGES: dict[str, tuple[tuple[str, tuple[str, ...]], ...]] = {
    "put": (("ingress", ("put",)),),
    "sub": (("ingress", ("declare_subscriber",)), ("egress", ("put",))),
    "serve": (("ingress", ("declare_queryable", "reply")), ("egress", ("query",))),
    "ask": (("ingress", ("query",)), ("egress", ("reply",))),
    "token": (("ingress", ("liveliness_token",)),),
    "watch": (("ingress", ("declare_liveliness_subscriber", "liveliness_query")), ("egress", ("liveliness_token",))),
    "discover": (("egress", ("declare_subscriber", "declare_queryable")),),
}


def _siblings(key: str) -> str:
    """``a/b/c`` -> ``a/b/*``: every key next to one that :class:`Keys` spells."""
    return key.rsplit("/", 1)[0] + "/*"


def grants(keys: Keys, robot_ids: Sequence[int]) -> dict[str, Grant]:
    """The grant of every user of a run with these robots (see the module docstring)."""
    render_all = _siblings(keys.render(0))
    out = {
        WORLD: Grant(
            put=(keys.tick(), keys.world_status(), keys.world_applied(), render_all, keys.images(), keys.encoders(),
                 keys.truth(), _siblings(keys.ack("render/0"))),
            sub=(keys.cmd(), keys.world_command(), keys.acks(), render_all),
            token=(keys.alive("world/0"), _siblings(keys.alive("render/0"))),
            watch=(keys.alive_all(),)),
        SERVER: Grant(
            put=(keys.map(), keys.server_status(), keys.correction(), keys.ack("server/0")),
            sub=(keys.observation(), keys.odometry(), keys.tick(), _siblings(keys.ack("agent/0"))),
            serve=(keys.map(),),
            token=(keys.alive("server/0"),),
            watch=(keys.alive_all(),)),
        VIEWER: Grant(sub=(keys.all(),), ask=(keys.map(),), watch=(keys.all(),)),
        OPERATOR: Grant(put=(keys.goal(), keys.world_command()), sub=(keys.all(),), ask=(keys.map(),),
                        watch=(keys.all(),)),
        RECORDER: Grant(sub=(keys.all(),), ask=(keys.map(),), serve=(claim_key(keys),),
                        token=(keys.alive(RECORDER_PARTICIPANT),), watch=(keys.all(),)),
        CLAIMANT: Grant(ask=(claim_key(keys),), watch=(keys.alive_all(),)),
    }
    for rid in robot_ids:
        me = f"agent/{int(rid)}"
        out[agent_user(rid)] = Grant(
            put=(keys.observation(rid), keys.odometry(rid), keys.robot_status(rid), keys.cmd(rid), keys.ack(me)),
            sub=(keys.images(rid), keys.encoders(rid), keys.tick(), keys.correction(rid), keys.goal(rid),
                 keys.map(), keys.recorded_cmd(rid)),
            ask=(keys.map(),),
            token=(keys.alive(me),),
            watch=(keys.alive_all(),))
    everything = (keys.all(),)
    return {u: dataclasses.replace(out[u], discover=everything) for u in users(robot_ids)}


def access_control(keys: Keys, robot_ids: Sequence[int]) -> dict[str, Any]:
    """The Zenoh 1.x ``access_control`` block: deny by default, one subject per user
    (matched on the authenticated user name), one allow rule per user, operation and
    flow, one policy per user tying them together."""
    rules: list[dict[str, Any]] = []
    subjects: list[dict[str, Any]] = []
    policies: list[dict[str, Any]] = []
    for user, grant in grants(keys, robot_ids).items():
        ids = []
        for f in fields(Grant):
            key_exprs: tuple[str, ...] = getattr(grant, f.name)
            if not key_exprs:
                continue
            for flow, messages in _MESSAGES[f.name]:
                rule_id = f"{user}:{f.name}:{flow}"
                rules.append({"id": rule_id, "permission": "allow", "flows": [flow], "messages": list(messages),
                              "key_exprs": list(key_exprs)})
                ids.append(rule_id)
        subjects.append({"id": user, "usernames": [user]})
        policies.append({"id": user, "rules": ids, "subjects": [user]})
    return {"enabled": True, "default_permission": "deny", "rules": rules, "subjects": subjects,
            "policies": policies}


def router_config(keys: Keys, robot_ids: Sequence[int], *, listen: Sequence[str], users_file: str) -> dict[str, Any]:
    """A complete Zenoh router config (for ``zenohd -c`` or ``tagswarm router
    --zenoh-config``): router mode, ``listen`` endpoints, multicast scouting off,
    user/password authentication against ``users_file`` and the ACL."""
    return {
        "mode": "router",
        "listen": {"endpoints": list(listen)},
        "scouting": {"multicast": {"enabled": False}},
        "transport": {"auth": {"usrpwd": {"dictionary_file": users_file}}},
        "access_control": access_control(keys, robot_ids),
    }


def render_config(config: dict[str, Any], header: str) -> str:
    """``config`` as a JSON5 file under ``header`` comment lines: plain JSON (valid JSON5),
    objects one member per line, lists of plain values on one line, so a rule reads
    as a block."""
    lines = [f"// {line}".rstrip() for line in header.splitlines()]
    return "\n".join(lines) + "\n" + _json(config, 0) + "\n"


def _json(value: Any, depth: int) -> str:
    pad, inner = "  " * depth, "  " * (depth + 1)
    if isinstance(value, dict):
        body = ",\n".join(f"{inner}{json.dumps(k)}: {_json(v, depth + 1)}" for k, v in value.items())
        return "{\n" + body + "\n" + pad + "}"
    if isinstance(value, list) and any(isinstance(v, dict | list) for v in value):
        return "[\n" + ",\n".join(inner + _json(v, depth + 1) for v in value) + "\n" + pad + "]"
    return json.dumps(value)


def make_secrets(folder: Path, user_names: Sequence[str]) -> list[Path]:
    """Create ``folder/<user>.password`` for every user that has none yet (random,
    URL-safe, so never a ``:``) and rewrite ``folder/users.txt``, the router's
    ``user:password`` dictionary, from all of them, and ``folder/agents.txt``, its agent
    lines (the claim authority's, :mod:`tagswarm.deploy.claims`).  Existing passwords are kept.

    ``folder`` is made private (0700).  The files in it are 0644 on purpose: compose
    bind-mounts each secret with its host owner and mode, and the containers run as
    an unprivileged user that could not read a 0600 file it does not own; the
    private folder keeps other host users out.  Returns the files written."""
    folder.mkdir(parents=True, exist_ok=True)
    folder.chmod(0o700)
    written = []
    entries = []
    for user in user_names:
        path = folder / f"{user}{PASSWORD_SUFFIX}"
        if not path.exists():
            _write(path, secrets.token_urlsafe(24) + "\n")
            written.append(path)
        entries.append(f"{user}:{path.read_text().strip()}")
    users_path = folder / USERS_FILE
    _write(users_path, "\n".join(entries) + "\n")
    written.append(users_path)
    agents = [e for e in entries if AGENT_USER.fullmatch(e.split(":", 1)[0])]
    _write(folder / AGENTS_FILE, "".join(f"{e}\n" for e in agents))
    written.append(folder / AGENTS_FILE)
    return written


def _write(path: Path, text: str) -> None:
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o644)
    with os.fdopen(fd, "w") as fh:
        fh.write(text)
    path.chmod(0o644)

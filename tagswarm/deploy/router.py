"""``tagswarm router``: a Zenoh router (in Python, through tagswarm.protocol.bus) for client-mode processes.

    tagswarm router --listen tcp/0.0.0.0:7447 --heartbeat /tmp/tagswarm-router.heartbeat

Every process started with ``--zenoh-mode client --connect tcp/<router>:7447``
(compose: ``TAGSWARM_ZENOH_MODE=client``, ``TAGSWARM_CONNECT``) sends and
receives all its traffic through this router; multicast scouting stays off
unless asked for.  The router always runs in Zenoh's router mode (the
``TAGSWARM_ZENOH_MODE`` variable is ignored here), listens on ``--listen``
(default ``tcp/0.0.0.0:7447``), may ``--connect`` to other routers, declares
the liveliness token ``tagswarm/<run>/alive/router/0`` and runs until SIGTERM
or SIGINT (exit 0).  With ``--heartbeat PATH`` it touches PATH every second
(for ``tagswarm alive --heartbeat PATH`` healthchecks) and removes it on exit.
With ``--until-gone recorder/0`` it also exits 0 once that participant has
come and gone (compose: the run is over and its folder written).

Security (docs/security.md):

    tagswarm router --make-secrets deploy/secrets          # one password per role + users.txt
    tagswarm router --users deploy/secrets/users.txt --acl # authenticate, then enforce the ACL
    tagswarm router --users FILE --acl --print-config      # the same as a Zenoh JSON5 config

``--users FILE`` (Zenoh's ``user:password`` dictionary) admits only clients that
log in with one of its entries (``--zenoh-user``, ``--zenoh-password-file``);
``--acl`` adds the access control of tagswarm/deploy/acl.py for the run (``--run``) and
the scenario's robots (``--scenario``, ``--robots``): each role may publish,
subscribe, query and declare only its own keys.
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import sys
import threading
from collections.abc import Sequence
from pathlib import Path

import msgspec

from tagswarm.deploy import acl
from tagswarm.protocol.bus import Bus, BusConfig, open_bus
from tagswarm.protocol.keys import Keys, split_participant
from tagswarm.runtime.config import (
    ConfigError,
    Invocation,
    OneLineParser,
    add_common_args,
    bus_from,
    pick,
    scenario_from,
)
from tagswarm.runtime.process import install_stop_signals, run_main, setup_logging

PROG = "tagswarm router"
DEFAULT_LISTEN = "tcp/0.0.0.0:7447"
HEARTBEAT_PERIOD_S = 1.0
PARTICIPANT = "router/0"

log = logging.getLogger("tagswarm.router")


def parser() -> OneLineParser:
    p = OneLineParser(prog=PROG, description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--heartbeat", metavar="PATH", help="touch PATH every second while the router runs")
    p.add_argument("--until-gone", metavar="ROLE/ID", help="exit 0 once this participant's liveliness token, "
                   "after it was seen, goes away (compose: the recorder, so `docker compose up` ends with the run)")
    s = p.add_argument_group("security (docs/security.md)")
    s.add_argument("--users", metavar="FILE", help="Zenoh user:password dictionary: only clients that log in "
                   "with one of its entries may connect (env TAGSWARM_ZENOH_USERS_FILE)")
    s.add_argument("--acl", action="store_true", help="enforce tagswarm's access control (needs --users): each "
                   "role may use only its own keys of this run and the scenario's robots")
    s.add_argument("--print-config", action="store_true",
                   help="print the router's Zenoh JSON5 config (listen, auth, ACL) and exit")
    s.add_argument("--make-secrets", metavar="DIR", help="write a password file per role of the scenario's "
                   "robots (kept if present) and the users.txt dictionary into DIR, then exit")
    add_common_args(p)
    return p


def router_config(args: argparse.Namespace, env: dict[str, str], *, check_files: bool = True) -> BusConfig:
    """The router's bus settings: the common network flags, forced into router mode,
    with authentication (``--users``) and the ACL (``--acl``) if asked for.
    ``check_files=False`` accepts a users file that is not here (a config printed
    for another machine or container)."""
    if args.zenoh_mode not in (None, "router"):
        raise ConfigError(f"--zenoh-mode {args.zenoh_mode}: a router runs in router mode")
    # a compose-wide environment may carry a client's mode and credentials: not the router's
    ignored = ("TAGSWARM_ZENOH_MODE", "TAGSWARM_ZENOH_USER", "TAGSWARM_ZENOH_PASSWORD_FILE")
    base = bus_from(args, {k: v for k, v in env.items() if k not in ignored})
    users_file = args.users or env.get("TAGSWARM_ZENOH_USERS_FILE") or None
    if check_files and users_file is not None and not os.path.isfile(users_file):
        raise ConfigError(f"--users: no such file {users_file!r}")
    if args.acl and users_file is None:
        raise ConfigError("--acl needs --users: the ACL grants rights to authenticated user names")
    rules = None
    if args.acl:
        rules = json.dumps(acl.access_control(Keys(pick(args, env, "run", "default")), robot_ids(args, env)))
    return msgspec.structs.replace(base, mode="router", listen=base.listen or (DEFAULT_LISTEN,),
                                   users_file=users_file, access_control=rules)


def robot_ids(args: argparse.Namespace, env: dict[str, str]) -> tuple[int, ...]:
    """The robots of the scenario (``--scenario``, ``--robots``, TAGSWARM_* variables)."""
    return scenario_from(args, env).robot_ids


def print_config(cfg: BusConfig, keys: Keys, robots: Sequence[int], command: str) -> str:
    """The router's Zenoh config as JSON5 text (what ``--print-config`` prints);
    ``command`` is the command line that regenerates it."""
    config = acl.router_config(keys, robots, listen=cfg.listen, users_file=cfg.users_file or "users.txt")
    if cfg.access_control is None:
        del config["access_control"]
    if cfg.users_file is None:
        del config["transport"]
    header = (f"Zenoh router config for tagswarm run {keys.run!r}, robots {list(robots)}, generated from\n"
              f"protocol/keys.py by `{command}`: do not edit, regenerate.\n"
              "Use: zenohd -c FILE, or tagswarm router --zenoh-config FILE.  See docs/security.md.")
    return acl.render_config(config, header)


class GoneWatch:
    """Has a liveliness token been seen and then dropped?"""

    def __init__(self, bus: Bus, key: str) -> None:
        self.key = key
        self.inbox = bus.watch_liveliness(key)
        self.seen = False

    def gone(self) -> bool:
        for change in self.inbox.drain():
            if change.value:
                self.seen = True
            elif self.seen:
                log.info("%s left: stopping", self.key)
                return True
        return False


class Heartbeat:
    """A file whose modification time says the router is alive."""

    def __init__(self, path: str) -> None:
        self.path = Path(path)

    def beat(self) -> None:
        self.path.touch()

    def clear(self) -> None:
        self.path.unlink(missing_ok=True)


def serve(cfg: BusConfig, keys: Keys, stop: threading.Event, heartbeat: Heartbeat | None,
          until_gone: str | None = None) -> int:
    """Run the router until ``stop`` (or ``until_gone``'s token came and went); returns 0."""
    with open_bus(cfg) as bus:
        bus.declare_token(keys.alive(PARTICIPANT))
        watch = GoneWatch(bus, keys.alive(until_gone)) if until_gone is not None else None
        security = ("ACL on, users from " if cfg.access_control else "users from ") + str(cfg.users_file) \
            if cfg.users_file else "no authentication"
        log.info("Zenoh router %s listening on %s%s (run %r, %s)", bus.zid, ", ".join(cfg.listen),
                 f", connected to {', '.join(cfg.connect)}" if cfg.connect else "", keys.run, security)
        try:
            while not stop.is_set() and not (watch is not None and watch.gone()):
                if heartbeat is not None:
                    try:
                        heartbeat.beat()
                    except OSError as exc:
                        log.warning("cannot touch heartbeat %s: %s", heartbeat.path, exc.strerror)
                stop.wait(HEARTBEAT_PERIOD_S)
        finally:
            if heartbeat is not None:
                heartbeat.clear()
    log.info("router stopped")
    return 0


def main(argv: Sequence[str] | None = None) -> int:
    """Console entry for ``tagswarm router``."""

    def body() -> int:
        inv = Invocation(parser(), argv)
        args = inv.args
        env = inv.env
        keys = Keys(inv.pick("run", "default"))
        if args.make_secrets:
            folder = Path(args.make_secrets)
            try:
                written = acl.make_secrets(folder, acl.users(robot_ids(args, env)))
            except OSError as exc:
                raise ConfigError(f"--make-secrets: cannot write {folder}: {exc.strerror}") from None
            print(f"{len(written) - 2} new password file(s), {folder / acl.USERS_FILE} and "
                  f"{folder / acl.AGENTS_FILE} written")
            return 0
        if args.until_gone is not None:
            split_participant(args.until_gone)
        cfg = router_config(args, env, check_files=not args.print_config)
        if args.print_config:
            command = " ".join([PROG, *(sys.argv[1:] if argv is None else argv)])
            sys.stdout.write(print_config(cfg, keys, robot_ids(args, env), command))
            return 0
        setup_logging(inv.log_level("INFO"), "router")
        heartbeat = Heartbeat(args.heartbeat) if args.heartbeat else None
        if heartbeat is not None:
            try:  # fail early, with one line; the first real beat comes once the router is up
                heartbeat.beat()
                heartbeat.clear()
            except OSError as exc:
                raise ConfigError(f"--heartbeat: cannot write {args.heartbeat}: {exc.strerror}") from None
        stop = threading.Event()
        install_stop_signals(stop)
        try:
            return serve(cfg, keys, stop, heartbeat, args.until_gone)
        finally:
            if heartbeat is not None:
                heartbeat.clear()

    return run_main(PROG, body)


if __name__ == "__main__":
    raise SystemExit(main())

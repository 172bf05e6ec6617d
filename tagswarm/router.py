"""``tagswarm router``: a Zenoh router (in Python, through protocol.bus) for client-mode processes.

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
"""

from __future__ import annotations

import argparse
import logging
import threading
from collections.abc import Sequence
from pathlib import Path

import msgspec

from protocol.bus import BusConfig, open_bus
from protocol.config import (
    ConfigError,
    OneLineParser,
    add_common_args,
    bus_from,
    env_of,
    install_stop_signals,
    pick,
    run_main,
    setup_logging,
)
from protocol.keys import Keys

PROG = "tagswarm router"
DEFAULT_LISTEN = "tcp/0.0.0.0:7447"
HEARTBEAT_PERIOD_S = 1.0
PARTICIPANT = "router/0"

log = logging.getLogger("tagswarm.router")


def parser() -> OneLineParser:
    p = OneLineParser(prog=PROG, description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--heartbeat", metavar="PATH", help="touch PATH every second while the router runs")
    add_common_args(p)
    return p


def router_config(args: argparse.Namespace, env: dict[str, str]) -> BusConfig:
    """The router's bus settings: the common network flags, forced into router mode."""
    if args.zenoh_mode not in (None, "router"):
        raise ConfigError(f"--zenoh-mode {args.zenoh_mode}: a router runs in router mode")
    base = bus_from(args, {k: v for k, v in env.items() if k != "TAGSWARM_ZENOH_MODE"})
    return msgspec.structs.replace(base, mode="router", listen=base.listen or (DEFAULT_LISTEN,))


class Heartbeat:
    """A file whose modification time says the router is alive."""

    def __init__(self, path: str) -> None:
        self.path = Path(path)

    def beat(self) -> None:
        self.path.touch()

    def clear(self) -> None:
        self.path.unlink(missing_ok=True)


def serve(cfg: BusConfig, keys: Keys, stop: threading.Event, heartbeat: Heartbeat | None) -> int:
    """Run the router until ``stop``; returns 0."""
    with open_bus(cfg) as bus:
        bus.declare_token(keys.alive(PARTICIPANT))
        log.info("Zenoh router %s listening on %s%s (run %r)", bus.zid, ", ".join(cfg.listen),
                 f", connected to {', '.join(cfg.connect)}" if cfg.connect else "", keys.run)
        try:
            while not stop.is_set():
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
        args = parser().parse_args(list(argv) if argv is not None else None)
        env = env_of()
        cfg = router_config(args, env)
        keys = Keys(pick(args, env, "run", "default"))
        setup_logging(pick(args, env, "log_level", "INFO"), "router")
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
            return serve(cfg, keys, stop, heartbeat)
        finally:
            if heartbeat is not None:
                heartbeat.clear()

    return run_main(PROG, body)


if __name__ == "__main__":
    raise SystemExit(main())

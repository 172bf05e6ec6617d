"""The server process's one frozen config."""

from __future__ import annotations

import argparse
from collections.abc import Mapping, Sequence
from pathlib import Path

import msgspec

from tagswarm.protocol.bus import BusConfig
from tagswarm.protocol.scenario import Scenario
from tagswarm.runtime.config import ConfigError, Invocation, OneLineParser, add_common_args


class ServerConfig(msgspec.Struct, frozen=True, kw_only=True):
    scenario: Scenario
    bus: BusConfig
    run: str = "default"
    log_level: str = "INFO"
    map_rate_hz: float = 2.0
    update_rate_hz: float = 10.0
    lag_s: float = 30.0
    participant: str = "server/0"
    journal: str | None = None  # write-ahead journal file; replayed at start if it exists
    journal_sync_every: int = 64  # fsync after this many records ...
    journal_sync_ms: float = 100.0  # ... or this long after the oldest unsynced one (wall time: I/O only)
    # a checkpoint of the whole fusion state every this many simulated seconds (0: never), so that a
    # restart replays at most this much of the journal
    journal_checkpoint_s: float = 10.0


def parser(prog: str = "tagswarm-server") -> argparse.ArgumentParser:
    p = OneLineParser(
        prog=prog,
        description="The tagswarm map server: stitches every robot's relative observations and odometry into one "
        "global map and pushes map->odom corrections back.  The scenario's [server] method chooses how: 'graph' "
        "(default; GTSAM iSAM2 fixed-lag pose graph) or 'stitch' (the paper: the newest observations composed along "
        "the who-sees-whom chain, odometry in between; no journal), e.g. --set server.method='\"stitch\"'.")
    add_common_args(p)
    p.add_argument("--map-rate", type=float, default=2.0, metavar="HZ", help="global map publish rate (default 2)")
    p.add_argument("--update-rate", type=float, default=10.0, metavar="HZ",
                   help="fusion updates per simulated second in realtime mode (default 10; lockstep: every tick)")
    p.add_argument("--lag", type=float, default=30.0, metavar="SECONDS",
                   help="fixed-lag window of the smoother in simulated seconds (default 30)")
    j = p.add_argument_group("journal (crash recovery)")
    j.add_argument("--journal", metavar="PATH",
                   help="append every accepted observation and odometry sample to PATH; if PATH exists, first "
                        "rebuild the map by replaying it (same run, scenario and fusion settings only) "
                        "(env TAGSWARM_JOURNAL; default: no journal)")
    j.add_argument("--journal-sync-every", type=int, default=64, metavar="N",
                   help="fsync the journal after N records (default 64) ...")
    j.add_argument("--journal-sync-ms", type=float, default=100.0, metavar="MS",
                   help="... or MS milliseconds after the oldest record not yet on disk (default 100)")
    j.add_argument("--journal-checkpoint", type=float, default=None, metavar="S",
                   help="write a checkpoint of the whole map state every S simulated seconds, so that a restarted "
                        "server replays at most S seconds of the journal (env TAGSWARM_JOURNAL_CHECKPOINT; "
                        "default 10; 0 = never: a restart replays the whole journal)")
    return p


def _journal_path(inv: Invocation) -> str | None:
    raw = inv.pick("journal", None)
    if not raw:
        return None
    path = Path(raw)
    if path.is_dir():
        raise ConfigError(f"--journal: {raw} is a directory, expected a file")
    parent = path.parent if str(path.parent) else Path(".")
    if not parent.is_dir():
        raise ConfigError(f"--journal: folder {parent} does not exist")
    return str(path)


def build_config(argv: Sequence[str] | None = None, environ: Mapping[str, str] | None = None) -> ServerConfig:
    inv = Invocation(parser(), argv, environ)
    args = inv.args
    scenario = inv.scenario()
    for name in ("map_rate", "update_rate", "lag"):
        if getattr(args, name) <= 0:
            raise ConfigError(f"--{name.replace('_', '-')} must be > 0")
    if args.journal_sync_every < 1:
        raise ConfigError("--journal-sync-every must be >= 1")
    if not args.journal_sync_ms >= 0:
        raise ConfigError("--journal-sync-ms must be >= 0")
    raw_checkpoint = inv.pick("journal_checkpoint", 10.0)
    try:
        checkpoint_s = float(raw_checkpoint)
    except ValueError:
        raise ConfigError(f"--journal-checkpoint: {raw_checkpoint!r} is not a number") from None
    if not 0 <= checkpoint_s < float("inf"):
        raise ConfigError("--journal-checkpoint must be >= 0 seconds (0 = no checkpoints)")
    run = inv.run()
    return ServerConfig(scenario=scenario, bus=inv.bus(), run=run, log_level=inv.log_level(), map_rate_hz=args.map_rate,
                        update_rate_hz=args.update_rate, lag_s=args.lag, journal=_journal_path(inv),
                        journal_sync_every=args.journal_sync_every, journal_sync_ms=args.journal_sync_ms,
                        journal_checkpoint_s=checkpoint_s)

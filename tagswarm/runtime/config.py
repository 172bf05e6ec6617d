"""A process's configuration from its command line and environment, shared by every ``main``.

Precedence, lowest first: the scenario TOML, ``TAGSWARM_*`` environment
variables, command-line flags.  Everything funnels into dotted scenario
overrides (``clock.mode=lockstep``) plus a :class:`~tagswarm.protocol.busconfig.BusConfig`, so
each process builds one frozen config object up front.  Errors become
:class:`ConfigError` (one line, naming the field);
:func:`tagswarm.runtime.process.run_main` turns them into exit code 2.
"""

from __future__ import annotations

import argparse
import os
import re
import sys
from collections.abc import Mapping, Sequence
from typing import Any, Literal, NoReturn

from tagswarm.protocol.bus import (
    DEFAULT_LEASE_MS,
    MAX_DELAY_MS,
    MAX_LEASE_MS,
    MIN_LEASE_MS,
    BusConfig,
    BusError,
    check_key_expr,
)
from tagswarm.protocol.errors import UsageError
from tagswarm.protocol.keys import Keys
from tagswarm.protocol.scenario import Scenario, ScenarioError, convert, load_scenario

ENV_PREFIX = "TAGSWARM_"
#: the shape of a Zenoh endpoint (protocol/address, optional #config), checked before Zenoh's own parser,
#: whose errors are Rust debug dumps
ENDPOINT = re.compile(r"[a-z][a-z0-9-]*/\S+")


class ConfigError(UsageError, ValueError):
    """Bad configuration or command line; the message is one line."""


class OneLineParser(argparse.ArgumentParser):
    """argparse that reports errors as a single line and exits with code 2, and takes no
    abbreviated flags (``--robot 3`` must not quietly mean ``--robots 3``)."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        kwargs.setdefault("allow_abbrev", False)
        super().__init__(*args, **kwargs)

    def error(self, message: str) -> NoReturn:
        sys.stderr.write(f"{self.prog}: error: {message} (see --help)\n")
        raise SystemExit(2)


def add_common_args(p: argparse.ArgumentParser, *, scenario: Literal["run", "file", "none"] = "run",
                    faults: bool = True) -> None:
    """Flags every process understands (scenario, overrides, network, logging).  A tool that
    runs nothing takes fewer, so a flag that would do nothing is an error, not ignored:
    ``scenario="file"`` only ``--scenario`` and ``--set`` (it reads the scenario, runs none),
    ``"none"`` no scenario flags; ``faults=False`` no fault injection."""
    if scenario != "none":
        g = p.add_argument_group("scenario (TOML < TAGSWARM_* environment < these flags)")
        g.add_argument("--scenario",
                       help="built-in scenario name or .toml path (default: paper; env TAGSWARM_SCENARIO)")
        g.add_argument("--set", dest="overrides", action="append", default=[], metavar="FIELD=VALUE",
                       help="override any scenario field, e.g. --set clock.mode=lockstep (repeatable; "
                            "env TAGSWARM_SET='a.b=1;c.d=2')")
    if scenario == "run":
        g.add_argument("--seed", type=int, help="random seed (env TAGSWARM_SEED)")
        g.add_argument("--robots", type=int, help="number of robots (env TAGSWARM_ROBOTS)")
        g.add_argument("--clock", choices=("realtime", "lockstep"), help="clock mode (env TAGSWARM_CLOCK)")
        g.add_argument("--duration", type=float, metavar="SECONDS",
                       help="simulated seconds to run (env TAGSWARM_DURATION)")
    n = p.add_argument_group("network (Zenoh)")
    n.add_argument("--run", help="run id: namespaces every key so runs can share a network (env TAGSWARM_RUN; "
                                 "default: default)")
    n.add_argument("--zenoh-mode", choices=("peer", "client", "router"), help="Zenoh mode (env TAGSWARM_ZENOH_MODE)")
    n.add_argument("--listen", action="append", metavar="ENDPOINT", help="endpoint to listen on, e.g. "
                   "tcp/127.0.0.1:7447 (repeatable; env TAGSWARM_LISTEN, comma-separated)")
    n.add_argument("--connect", action="append", metavar="ENDPOINT",
                   help="endpoint to connect to (repeatable; env TAGSWARM_CONNECT, comma-separated)")
    n.add_argument("--multicast-scouting", action="store_true", default=None,
                   help="enable Zenoh multicast scouting (off by default)")
    n.add_argument("--zenoh-config", metavar="FILE", help="Zenoh JSON5 config file (also ZENOH_CONFIG)")
    n.add_argument("--zenoh-user", metavar="NAME",
                   help="Zenoh user presented to the router (env TAGSWARM_ZENOH_USER; see docs/security.md)")
    n.add_argument("--zenoh-password-file", metavar="FILE",
                   help="file holding that user's password (env TAGSWARM_ZENOH_PASSWORD_FILE)")
    n.add_argument("--zenoh-lease-ms", metavar="MS",
                   help="Zenoh link lease this process announces: peers drop it (and its liveliness) after "
                        f"that long without hearing from it ({MIN_LEASE_MS}..{MAX_LEASE_MS}; env "
                        f"TAGSWARM_ZENOH_LEASE_MS; default {DEFAULT_LEASE_MS})")
    if faults:
        f = p.add_argument_group("network fault injection (on what this process receives; for tests and demos)")
        f.add_argument("--net-loss", metavar="SHARE",
                       help="share of matching messages lost, 0..1 (env TAGSWARM_NET_LOSS)")
        f.add_argument("--net-delay-ms", metavar="MS", help="delay added to matching messages in milliseconds "
                                                           "(env TAGSWARM_NET_DELAY_MS)")
        f.add_argument("--net-jitter-ms", metavar="MS",
                       help="spread of that delay: each message late by delay ± jitter (uniform, seeded; per-key "
                            "order kept; env TAGSWARM_NET_JITTER_MS)")
        f.add_argument("--net-fault-keys", action="append", metavar="KEYEXPR",
                       help="key expression the faults apply to (repeatable; env TAGSWARM_NET_FAULT_KEYS, "
                            "comma-separated; default: encoders, wheel commands, goals, observations, odometry "
                            "and the map; never the clock, corrections or images)")
        f.add_argument("--net-seed", metavar="N", help="seed of the loss pattern (env TAGSWARM_NET_SEED; default 0)")
    p.add_argument("--log-level", default=None, help="DEBUG, INFO, WARNING... (env TAGSWARM_LOG_LEVEL; default INFO)")


def _env_list(env: Mapping[str, str], name: str) -> tuple[str, ...]:
    raw = env.get(ENV_PREFIX + name, "")
    return tuple(x.strip() for x in raw.split(",") if x.strip())


def pick(args: argparse.Namespace, env: Mapping[str, str], attr: str, default: Any = None) -> Any:
    """Flag value if given, else ``TAGSWARM_<ATTR>``, else ``default``."""
    value = getattr(args, attr, None)
    if value is not None:
        return value
    return env.get(ENV_PREFIX + attr.upper(), default)


def scenario_from(args: argparse.Namespace, env: Mapping[str, str]) -> Scenario:
    """Load the scenario and apply environment then CLI overrides."""
    name = pick(args, env, "scenario", "paper")
    overrides: list[str] = [o for o in env.get(ENV_PREFIX + "SET", "").split(";") if o.strip()]
    for attr, field in (("seed", "seed"), ("robots", "robots.count"), ("clock", "clock.mode"),
                        ("duration", "duration_s")):
        env_value = env.get(ENV_PREFIX + attr.upper())
        if env_value is not None:
            overrides.append(f"{field}={_quote(field, env_value)}")
    overrides += list(getattr(args, "overrides", None) or [])
    for attr, field in (("seed", "seed"), ("robots", "robots.count"), ("clock", "clock.mode"),
                        ("duration", "duration_s")):
        value = getattr(args, attr, None)
        if value is not None:
            overrides.append(f"{field}={_quote(field, str(value))}")
    return load_scenario(name, overrides)


def _quote(field: str, value: str) -> str:
    return f'"{value}"' if field == "clock.mode" else value


def bus_from(args: argparse.Namespace, env: Mapping[str, str]) -> BusConfig:
    """The Zenoh settings from flags and environment."""
    table: dict[str, Any] = {
        "mode": pick(args, env, "zenoh_mode", "peer"),
        "listen": list(args.listen or _env_list(env, "LISTEN")),
        "connect": list(args.connect or _env_list(env, "CONNECT")),
        "multicast_scouting": bool(args.multicast_scouting
                                   or env.get(ENV_PREFIX + "MULTICAST_SCOUTING", "") in ("1", "true")),
    }
    for flag, endpoints in (("--listen", table["listen"]), ("--connect", table["connect"])):
        for ep in endpoints:
            if not ENDPOINT.fullmatch(ep):
                raise ConfigError(f"{flag} {ep!r}: a Zenoh endpoint is PROTOCOL/ADDRESS, e.g. tcp/127.0.0.1:7447")
    cfg_file = args.zenoh_config or None
    if cfg_file:
        if not os.path.exists(cfg_file):
            raise ConfigError(f"--zenoh-config: no such file {cfg_file!r}")
        table["config_file"] = cfg_file
    table.update(_credentials(args, env))
    table.update(_faults(args, env))
    lease = pick(args, env, "zenoh_lease_ms")
    if lease is not None:
        table["lease_ms"] = _integer(lease, "--zenoh-lease-ms", MIN_LEASE_MS, MAX_LEASE_MS, "milliseconds")
    try:
        bus: BusConfig = convert(table, BusConfig, "network")
    except ScenarioError as exc:
        raise ConfigError(str(exc)) from None
    return bus


def _credentials(args: argparse.Namespace, env: Mapping[str, str]) -> dict[str, Any]:
    """``user`` and ``password_file`` (both or neither; the file must be readable)."""
    user = pick(args, env, "zenoh_user") or None
    pw_file = pick(args, env, "zenoh_password_file") or None
    if user is None and pw_file is None:
        return {}
    if user is None or pw_file is None:
        raise ConfigError("--zenoh-user and --zenoh-password-file go together (env TAGSWARM_ZENOH_USER, "
                          "TAGSWARM_ZENOH_PASSWORD_FILE)")
    if ":" in user or not user.strip() or user != user.strip():
        raise ConfigError(f"--zenoh-user {user!r}: a user name has no ':' and no surrounding blanks")
    if not os.path.isfile(pw_file) or not os.access(pw_file, os.R_OK):
        raise ConfigError(f"--zenoh-password-file: cannot read {pw_file!r}")
    return {"user": user, "password_file": pw_file}


def _faults(args: argparse.Namespace, env: Mapping[str, str]) -> dict[str, Any]:
    """``loss``, ``delay_ms``, ``jitter_ms``, ``fault_keys`` and ``fault_seed``, validated with the flag's name."""
    out: dict[str, Any] = {}
    loss = pick(args, env, "net_loss")
    if loss is not None:
        out["loss"] = _number(loss, "--net-loss", 0.0, 1.0, "a share between 0 and 1")
    delay = pick(args, env, "net_delay_ms")
    if delay is not None:
        out["delay_ms"] = _number(delay, "--net-delay-ms", 0.0, MAX_DELAY_MS, f"milliseconds, 0..{MAX_DELAY_MS:g}")
    jitter = pick(args, env, "net_jitter_ms")
    if jitter is not None:
        limit = float(out.get("delay_ms", 0.0))
        out["jitter_ms"] = _number(jitter, "--net-jitter-ms", 0.0, limit, f"milliseconds, 0..the delay ({limit:g})")
    keys = list(args.net_fault_keys or _env_list(env, "NET_FAULT_KEYS")) if hasattr(args, "net_fault_keys") else []
    for k in keys:
        try:
            check_key_expr(k)
        except BusError as exc:
            raise ConfigError(f"--net-fault-keys: {exc}") from None
    if keys:
        out["fault_keys"] = keys
    seed = pick(args, env, "net_seed")
    if seed is not None:
        try:
            out["fault_seed"] = int(seed)
        except ValueError:
            raise ConfigError(f"--net-seed {seed!r}: must be an integer") from None
    return out


def _number(raw: Any, flag: str, low: float, high: float, what: str) -> float:
    try:
        value = float(raw)
    except (TypeError, ValueError):
        value = float("nan")
    if not low <= value <= high:  # also rejects nan
        raise ConfigError(f"{flag} {raw}: must be {what}")
    return value


def _integer(raw: Any, flag: str, low: int, high: int, what: str) -> int:
    try:
        value = int(str(raw).strip())
    except ValueError:
        raise ConfigError(f"{flag} {raw!r}: must be an integer ({what}, {low}..{high})") from None
    if not low <= value <= high:
        raise ConfigError(f"{flag} {raw}: must be {what}, {low}..{high}")
    return value


def env_of(environ: Mapping[str, str] | None = None) -> dict[str, str]:
    """The ``TAGSWARM_*`` part of the environment."""
    src = os.environ if environ is None else environ
    return {k: v for k, v in src.items() if k.startswith(ENV_PREFIX)}


def parse(parser: argparse.ArgumentParser, argv: Sequence[str] | None) -> argparse.Namespace:
    """Parse ``argv`` (``None`` means ``sys.argv[1:]``)."""
    return parser.parse_args(list(argv) if argv is not None else None)


class Invocation:
    """How a process was started: its parsed flags and its ``TAGSWARM_*`` environment, and
    what every process reads from them (a flag, else its variable, else the default)."""

    def __init__(self, parser: argparse.ArgumentParser, argv: Sequence[str] | None = None,
                 environ: Mapping[str, str] | None = None) -> None:
        self.args = parse(parser, argv)
        self.env = env_of(environ)

    def pick(self, attr: str, default: Any = None) -> Any:
        """Flag ``attr`` if given, else ``TAGSWARM_<ATTR>``, else ``default``."""
        return pick(self.args, self.env, attr, default)

    def scenario(self) -> Scenario:
        """The scenario with environment then flag overrides applied, validated."""
        return scenario_from(self.args, self.env)

    def bus(self) -> BusConfig:
        """The Zenoh settings."""
        return bus_from(self.args, self.env)

    def run(self, default: str = "default") -> str:
        """The run id, validated (it is part of every key: KeyNameError otherwise)."""
        run: str = self.pick("run", default)
        Keys(run)
        return run

    def log_level(self, default: str = "INFO") -> str:
        level: str = self.pick("log_level", default)
        return level

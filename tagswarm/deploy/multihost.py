"""A swarm across several "hosts" (network namespaces on this machine) and its run folder.

    python -m tagswarm.deploy.multihost --out DIR [--robots N] [--clock lockstep|realtime]
        [--delay-ms D [--jitter-ms J] [--delay-spread-ms S]] [--loss P] [--duration S] [--rate-mbit R]
        # scripts/multihost.sh

Hosts (:mod:`tagswarm.deploy.netns`, ``10.77.0.0/24``): ``router`` (.1: ``tagswarm router``
and the recorder ``tagswarm record-run``), ``world`` (.2: the world and its render
workers), ``server`` (.3), ``agent0``, ``agent1`` ... (.4 up).  Every process is a Zenoh
client of the router, started with the same command a person types on a real host
(:func:`commands`; ``multihost.json`` in the run folder lists them).  The run folder is
the one ``tagswarm up`` writes (the recorder writes it: :mod:`tagswarm.deploy.recordrun`),
plus ``logs/``, ``server.journal`` and ``multihost.json`` (hosts, links, commands, exit
codes, and in realtime the latency image -> correction and the real-time factor).

Link delay is the processes' receive-side fault layer (``--net-delay-ms`` on every key of
the run; ``--jitter-ms J`` spreads every message's delay over D ± J, seeded, each key's
order kept; with ``--delay-spread-ms S`` each host's delay is drawn once, seeded, from D ± S:
links differ;
the run: this kernel has no ``netem``); loss (``iptables statistic``) and bandwidth
(``tbf``) are the kernel's, on every host's link.  The harness itself watches the run as
one more client, through a Unix socket of the router (it cannot reach the namespaces'
addresses from the machine's own namespace, which it leaves untouched), delayed like an
agent: what it measures is what an agent sees.

Teardown: children are stopped (SIGTERM, then SIGKILL) and every namespace deleted on
exit, on an error, on SIGINT/SIGTERM; a SIGKILLed harness leaves its children to the
reaper (:mod:`tagswarm.runtime.procgroup`) and its namespaces to the next run, which
deletes namespaces of dead owners first.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import signal
import sys
import tempfile
import threading
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import msgspec

from tagswarm.deploy import netns
from tagswarm.deploy.hostplan import ROUTER_CONFIG, commands, host_delay_ms, host_names, resolve
from tagswarm.deploy.hostprobe import Probe
from tagswarm.protocol.bus import Bus, BusConfig, open_bus
from tagswarm.protocol.errors import TagswarmError
from tagswarm.protocol.keys import Keys
from tagswarm.protocol.layout import pinned
from tagswarm.protocol.scenario import Scenario
from tagswarm.runtime import procgroup
from tagswarm.runtime.config import ConfigError, OneLineParser, add_common_args, scenario_from
from tagswarm.runtime.process import run_main, setup_logging

PROG = "tagswarm multihost"
BIN = Path(sys.executable).parent


class MultiHostError(TagswarmError, RuntimeError):
    """The run failed: a process died unasked, or something did not happen in time (the
    message says what, with the tails of the logs)."""


class MultiHost:
    """One run across namespaces: ``with MultiHost(...) as mh: mh.start(); mh.wait_end()``.
    ``mh.probe`` watches the run (live record, latency); ``partition`` / ``heal`` a host,
    ``restart`` a process."""

    def __init__(self, out: Path, scenario: Scenario, *, run: str | None = None, delay_ms: float = 0.0,
                 loss: float = 0.0, rate_mbit: float | None = None, lease_ms: int | None = None,
                 latency: bool = False, report: bool = True, spread_ms: float = 0.0, jitter_ms: float = 0.0) -> None:
        self.out = out.resolve()
        self.scenario = pinned(resolve(scenario))  # scenario.json keeps the poses drawn today
        self.topo = netns.plan(netns.new_prefix(), host_names(self.scenario.robot_ids))
        self.run = run or f"mh{self.topo.prefix[3:]}"
        self.keys = Keys(self.run)
        self.links = netns.Links(loss=loss, rate_mbit=rate_mbit)
        self.delay_ms, self.lease_ms, self.latency, self.spread_ms = delay_ms, lease_ms, latency, spread_ms
        self.jitter_ms = jitter_ms
        self.sockdir = Path(tempfile.mkdtemp(prefix=f"{self.topo.prefix}-"))
        self.net = netns.Network(self.topo, self.links)
        self.children: dict[str, procgroup.Child] = {}
        self.restarts: dict[str, int] = {}
        self._bus_cm: Any = None
        self.bus: Bus | None = None
        self.probe: Probe | None = None
        self.t0 = time.monotonic()
        self.cmds = commands(self.topo, run=self.run, scenario_file=self.out / "scenario.json", out=self.out,
                             robots=self.scenario.robot_ids, delay_ms=delay_ms, lease_ms=lease_ms,
                             socket=self.sockdir / "router.sock", tagswarm=str(BIN / "tagswarm"), report=report,
                             spread_ms=spread_ms, seed=self.scenario.seed, jitter_ms=jitter_ms)

    # ---- life cycle
    def __enter__(self) -> MultiHost:
        self.out.mkdir(parents=True, exist_ok=True)
        (self.out / "logs").mkdir(exist_ok=True)
        (self.out / "scenario.json").write_bytes(msgspec.json.format(msgspec.json.encode(self.scenario)))
        (self.out / "server.journal").unlink(missing_ok=True)
        (self.out / "router.json5").write_text(ROUTER_CONFIG)
        self.net.__enter__()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def start(self, timeout_s: float = 120.0, stop: threading.Event | None = None) -> bool:
        """Router, then the recorder, server and agents, then the world (each once the previous are
        visible to the harness), as compose orders them.  False if ``stop`` was set on the way
        (Ctrl-C during the start: what was started is stopped by :meth:`close`)."""
        def stopped() -> bool:
            return stop is not None and stop.is_set()

        self.spawn("router")
        self._open_probe(timeout_s)
        self.spawn("recorder")
        self.until(lambda: stopped() or self.alive("recorder/0"), timeout_s, "the recorder never came up")
        if stopped():
            return False
        self.spawn("server")
        for r in self.scenario.robot_ids:
            self.spawn(f"agent/{r}")
        workers = ["server/0", *(f"agent/{r}" for r in self.scenario.robot_ids)]
        self.until(lambda: stopped() or all(self.alive(w) for w in workers), timeout_s,
                   "server and agents never all came up")
        if stopped():
            return False
        self.spawn("world")
        return True

    def spawn(self, name: str) -> procgroup.Child:
        """Start process ``name`` on its host (again, after :meth:`stop`)."""
        host, argv = self.cmds[name]
        n = self.restarts.get(name, 0)
        log = self.out / "logs" / (name.replace("/", "") + (f".{n}" if n else "") + ".log")
        env = {**{k: v for k, v in _environ().items() if not k.startswith("TAGSWARM_")}, "PYTHONUNBUFFERED": "1"}
        child = procgroup.Child(name, self.net.exec_argv(host, argv), log, env)
        self.children[name] = child
        self.restarts[name] = n + 1
        return child

    def stop(self, name: str, grace_s: float = 10.0) -> None:
        """Stop process ``name`` (SIGTERM, then SIGKILL)."""
        self.children[name].stop(grace_s)

    def restart(self, name: str) -> None:
        """Stop ``name`` and start it again with the same command."""
        self.stop(name)
        self.spawn(name)

    def partition(self, host: str) -> None:
        self.net.partition(host)

    def heal(self, host: str) -> None:
        self.net.heal(host)

    def close(self) -> None:
        """Stop everything still running and delete the namespaces (idempotent)."""
        try:
            for name in ("world", *[n for n in self.children if n.startswith("agent/")], "server", "recorder"):
                if name in self.children and self.children[name].poll() is None:
                    self.children[name].stop(5.0 if name != "recorder" else 60.0)
            self._close_probe()
            for child in self.children.values():
                child.stop(5.0)
        finally:
            self.net.close()
            shutil.rmtree(self.sockdir, ignore_errors=True)

    # ---- watching
    def _open_probe(self, timeout_s: float) -> None:
        cfg = BusConfig(mode="client", connect=(f"unixsock-stream/{self.sockdir / 'router.sock'}",),
                        delay_ms=self.delay_ms, fault_keys=(f"tagswarm/{self.run}/**",) if self.delay_ms else ())
        deadline = time.monotonic() + timeout_s
        while True:  # the router's socket appears once it listens
            try:
                self._bus_cm = open_bus(cfg)
                self.bus = self._bus_cm.__enter__()
                break
            except Exception:
                self._check_children()
                if time.monotonic() > deadline:
                    raise MultiHostError(f"the router never listened\n{self.tails()}") from None
                time.sleep(0.2)
        self.probe = Probe(self.bus, self.keys, self.scenario, latency=self.latency)

    def _close_probe(self) -> None:
        if self._bus_cm is not None:
            self._bus_cm.__exit__(None, None, None)
            self._bus_cm, self.bus = None, None

    def alive(self, participant: str) -> bool:
        """Whether ``participant``'s liveliness token is visible through the router now."""
        return self.probe is not None and participant in self.probe.alive

    def poll(self) -> None:
        if self.probe is not None:
            self.probe.poll()

    def until(self, cond: Callable[[], bool], timeout_s: float, what: str, *, check: bool = True) -> float:
        """Poll until ``cond()``; the wall seconds it took.  TimeoutError naming ``what`` (with
        the logs' tails), or an error as soon as a child died unasked (``check``)."""
        t0 = time.monotonic()
        while True:
            self.poll()
            if cond():
                return time.monotonic() - t0
            if check:
                self._check_children()
            if time.monotonic() - t0 > timeout_s:
                raise MultiHostError(f"{what} (after {timeout_s:g} s)\n{self.tails()}")
            if self.bus is not None:
                self.bus.wait(0.05)
            else:
                time.sleep(0.05)

    def _check_children(self) -> None:
        dead = [c for c in self.children.values() if c.poll() not in (None, 0) and not c.signalled]
        if dead:
            raise MultiHostError(", ".join(f"{c.name} exited with code {c.poll()}" for c in dead) + "\n" + self.tails())

    def tails(self, n: int = 8) -> str:
        return "\n".join(c.tail(n) for c in self.children.values())

    def wait_end(self, timeout_s: float) -> dict[str, int | None]:
        """Wait for the world to finish its duration and the recorder to write the run folder;
        then write ``multihost.json``.  Exit codes by process."""
        self.until(lambda: self.children["world"].poll() is not None, timeout_s, "the world never finished")
        self.until(lambda: self.children["recorder"].poll() is not None, 120, "the recorder never wrote the folder")
        # the recorder saw their tokens go: the processes themselves may still be closing
        self.until(lambda: all(c.poll() is not None for n, c in self.children.items() if n != "router"), 60,
                   "the swarm's processes did not exit after the run")
        return self.write_summary()

    def exit_codes(self) -> dict[str, int | None]:
        return {name: c.poll() for name, c in self.children.items()}

    def write_summary(self, extra: dict[str, Any] | None = None) -> dict[str, int | None]:
        """``multihost.json``: hosts, links, commands, exit codes, what the probe measured."""
        self.poll()
        codes = self.exit_codes()
        summary = {
            "run": self.run, "prefix": self.topo.prefix, "wall_s": round(time.monotonic() - self.t0, 2),
            "hosts": {h.name: {"namespace": h.ns, "address": h.addr} for h in self.topo.hosts},
            "links": {"delay_ms": self.delay_ms, "jitter_ms": self.jitter_ms, "delay_spread_ms": self.spread_ms,
                      "host_delay_ms": {h.name: host_delay_ms(h.name, self.delay_ms, self.spread_ms, self.scenario.seed)
                                        for h in self.topo.hosts if h.name != "router"},
                      "loss": self.links.loss, "rate_mbit": self.links.rate_mbit,
                      "lease_ms": self.lease_ms, "delay_by": "receive-side fault layer (--net-delay-ms)",
                      "loss_by": "iptables statistic on every host's eth0 input"},
            "commands": {name: {"host": host, "argv": argv} for name, (host, argv) in self.cmds.items()},
            "restarts": {k: v - 1 for k, v in self.restarts.items() if v > 1},
            "exit_codes": codes,
            "probe": self.probe.summary() if self.probe is not None else None,
            **(extra or {}),
        }
        (self.out / "multihost.json").write_text(json.dumps(summary, indent=1))
        return codes


def _environ() -> dict[str, str]:
    return dict(os.environ)


def parser() -> OneLineParser:
    p = OneLineParser(prog=PROG, description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--out", type=Path, required=True, metavar="DIR", help="the run folder to write")
    p.add_argument("--delay-ms", type=float, default=0.0, metavar="MS",
                   help="one-way delay between hosts, milliseconds (receive-side fault layer; default 0)")
    p.add_argument("--jitter-ms", type=float, default=0.0, metavar="MS",
                   help="every message's delay drawn from D +- MS (uniform, seeded, each key's order kept; default 0)")
    p.add_argument("--delay-spread-ms", type=float, default=0.0, metavar="MS",
                   help="each host's delay drawn once from D +- MS (seeded by the scenario's seed; default 0)")
    p.add_argument("--loss", type=float, default=0.0, metavar="SHARE",
                   help="share of packets each host drops on receive (iptables statistic; default 0)")
    p.add_argument("--rate-mbit", type=float, default=None, metavar="MBIT",
                   help="egress bandwidth of every host (tbf; default unlimited)")
    p.add_argument("--no-report", action="store_true", help="do not compute metrics and plots at the end")
    p.add_argument("--timeout", type=float, default=600.0, metavar="SECONDS",
                   help="give up when the run has not ended after this long (wall; default 600)")
    add_common_args(p)
    return p


def main(argv: Sequence[str] | None = None) -> int:
    """Console entry (``python -m tagswarm.deploy.multihost``, ``scripts/multihost.sh``)."""

    def body() -> int:
        args = parser().parse_args(argv)
        env = {k: v for k, v in _environ().items() if k.startswith("TAGSWARM_")}
        if not 0.0 <= args.delay_ms <= 60_000:
            raise ConfigError(f"--delay-ms {args.delay_ms:g}: must be 0..60000")
        if not 0.0 <= args.jitter_ms <= args.delay_ms:
            raise ConfigError(f"--jitter-ms {args.jitter_ms:g}: must be 0..--delay-ms")
        if not 0.0 <= args.delay_spread_ms <= args.delay_ms:
            raise ConfigError(f"--delay-spread-ms {args.delay_spread_ms:g}: must be 0..--delay-ms")
        if not 0.0 <= args.loss < 1.0:
            raise ConfigError(f"--loss {args.loss:g}: must be a share in [0, 1)")
        if args.rate_mbit is not None and not args.rate_mbit > 0:
            raise ConfigError(f"--rate-mbit {args.rate_mbit:g}: must be > 0")
        why = netns.check_available()
        if why is not None:
            raise ConfigError(why)
        setup_logging(args.log_level or "INFO", "multihost")
        scenario = scenario_from(args, env)
        lease = int(args.zenoh_lease_ms) if args.zenoh_lease_ms is not None else None
        stop = threading.Event()
        procgroup.REGISTRY.catch_term = False  # SIGTERM stops the run in order, like Ctrl-C
        signal.signal(signal.SIGINT, lambda *_: stop.set())
        signal.signal(signal.SIGTERM, lambda *_: stop.set())
        with MultiHost(args.out, scenario, run=args.run, delay_ms=args.delay_ms, loss=args.loss,
                       spread_ms=args.delay_spread_ms, jitter_ms=args.jitter_ms,
                       rate_mbit=args.rate_mbit, lease_ms=lease, report=not args.no_report,
                       latency=scenario.clock.mode == "realtime") as mh:
            print(f"{PROG}: {len(mh.topo.hosts)} hosts ({mh.topo.prefix}-*), run {mh.run!r}, "
                  f"{scenario.clock.mode}, run folder {mh.out}", flush=True)
            failure: str | None = None
            try:
                if mh.start(stop=stop):
                    mh.until(lambda: stop.is_set() or mh.children["world"].poll() is not None, args.timeout,
                             "the run did not end")
                if stop.is_set():
                    mh.children["recorder"].send(signal.SIGTERM)  # it writes what it has, exit 130
                mh.until(lambda: mh.children["recorder"].poll() is not None, 120, "the recorder never finished")
            except MultiHostError as exc:
                failure = str(exc)
            finally:
                codes = mh.write_summary({"failure": failure})
            print(json.dumps({"exit_codes": codes, "probe": mh.probe.summary() if mh.probe else None}), flush=True)
        if failure is not None:
            sys.stderr.write(f"{PROG}: run failed: {failure}\n")
            return 1
        return 130 if stop.is_set() else (0 if all(c == 0 for c in codes.values() if c is not None) else 1)

    return run_main(PROG, body)


if __name__ == "__main__":
    raise SystemExit(main())

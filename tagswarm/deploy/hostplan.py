"""What runs on which host of a multi-host run, as command lines (pure: no namespaces, no processes).

:func:`commands` gives every process of a run (router, recorder, server, agents, world) its
host and the exact command line a person would type there (tagswarm/deploy/multihost.py runs
them in network namespaces; README, *Several machines*, on real hosts); :data:`ROUTER_CONFIG`
is the router's Zenoh config on top of tagswarm's settings.
"""

from __future__ import annotations

import random
from collections.abc import Sequence
from pathlib import Path

import msgspec

from tagswarm.deploy import netns
from tagswarm.protocol.scenario import Scenario

PORT = 7447
#: The router's Zenoh config on top of tagswarm's settings.  A router forwards a BLOCK message
#: (ticks, encoders, corrections ...) on the receive task of the link it came in on; when a
#: host is cut off, its link's queue fills and, by Zenoh's default, that task waits up to 5 s
#: before closing the dead link: meanwhile the router reads nothing from that sender, every
#: other host's lease of it runs out and the whole swarm drops.  Closing the dead link after
#: 0.5 s (a third of the default 1.5 s lease) keeps the others running.
ROUTER_CONFIG = """{
  // tagswarm multi-host router (docs/multihost.md): give up on a blocked link after 0.5 s
  transport: { link: { tx: { queue: { congestion_control: { block: { wait_before_close: 500000 } } } } } },
}
"""

def host_names(robots: Sequence[int]) -> list[str]:
    """Router first (``10.77.0.1``), then world, server and one host per agent."""
    return ["router", "world", "server", *(f"agent{r}" for r in robots)]


def resolve(scenario: Scenario) -> Scenario:
    """The scenario as compose runs it: lockstep participants every agent and the server,
    the recorder an observer (the world waits for it before the first tick)."""
    table = msgspec.to_builtins(scenario)
    if not scenario.clock.participants:
        table["clock"]["participants"] = [f"agent/{r}" for r in scenario.robot_ids] + ["server/0"]
    if "recorder/0" not in scenario.clock.observers:
        table["clock"]["observers"] = [*scenario.clock.observers, "recorder/0"]
    out: Scenario = msgspec.convert(table, Scenario)
    return out


def commands(topo: netns.Topology, *, run: str, scenario_file: Path, out: Path, robots: Sequence[int],
             delay_ms: float = 0.0, lease_ms: int | None = None, socket: Path | None = None,
             tagswarm: str = "tagswarm", report: bool = True,
             spread_ms: float = 0.0, seed: int = 0, jitter_ms: float = 0.0) -> dict[str, tuple[str, list[str]]]:
    """Process name -> (host, command line): what runs where.  The same lines work on real
    hosts with the router's address in place of ``10.77.0.1``."""
    router = f"tcp/{topo.host('router').addr}:{PORT}"
    lease = ["--zenoh-lease-ms", str(lease_ms)] if lease_ms is not None else []
    common = ["--run", run, "--scenario", str(scenario_file), *lease]
    client = ["--zenoh-mode", "client", "--connect", router, *common]
    def delay(host: str) -> list[str]:
        # link delay: every key of the run, on receive, in every process of the swarm (the kernel has no netem)
        d = host_delay_ms(host, delay_ms, spread_ms, seed)
        jitter = ["--net-jitter-ms", f"{min(jitter_ms, d):g}"] if jitter_ms > 0 else []
        return ["--net-delay-ms", f"{d:g}", *jitter, "--net-fault-keys", f"tagswarm/{run}/**"] if d > 0 else []

    listen = ["--listen", f"tcp/0.0.0.0:{PORT}"] + (["--listen", f"unixsock-stream/{socket}"] if socket else [])
    cmds: dict[str, tuple[str, list[str]]] = {
        "router": ("router", [tagswarm, "router", *listen, "--zenoh-config", str(out / "router.json5"), *common]),
        "recorder": ("router", [tagswarm, "record-run", "--out", str(out), *client,
                                *([] if report else ["--no-report"])]),
        "server": ("server", [tagswarm, "server", *client, "--journal", str(out / "server.journal"),
                                        *delay("server")]),
    }
    for r in robots:
        cmds[f"agent/{r}"] = (f"agent{r}", [tagswarm, "agent", "--robot-id", str(r), *client,
                                                 *delay(f"agent{r}")])
    cmds["world"] = ("world", [tagswarm, "world", *client, *delay("world")])
    return cmds


def host_delay_ms(host: str, delay_ms: float, spread_ms: float, seed: int) -> float:
    """The receive delay of ``host``'s processes: ``delay_ms``, or with a spread one draw from
    ``delay_ms ± spread_ms`` seeded by ``seed`` and the host's name (never below 0), in ms."""
    if spread_ms <= 0:
        return delay_ms
    return round(max(0.0, delay_ms + random.Random(f"{seed}/{host}").uniform(-spread_ms, spread_ms)), 3)

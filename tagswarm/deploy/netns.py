"""Several "hosts" on one Linux machine: network namespaces joined by veth pairs and a bridge.

Each host is a network namespace of its own with one interface ``eth0`` and one address
in ``10.77.0.0/24`` (router ``.1``, then the other hosts in order).  The other end of
every host's veth pair sits in a hub namespace, enslaved to the bridge ``br0`` there,
so that nothing is added to the machine's own namespace (no address, no interface, no
rule).  Names carry a per-run prefix (``tsw<pid>x<n>``), so parallel runs never collide,
and a namespace whose owner pid is gone is recognised as stale (:func:`stale_prefixes`).

Link impairments, with what this kernel offers (no ``netem``, no ``fq_codel``; ``tbf``,
``htb`` and ``pfifo`` work; iptables' ``statistic`` match drops):

- loss: ``iptables -A INPUT -i eth0 -m statistic --mode random --probability P -j DROP``
  in every host, so each packet crossing the bridge is lost with probability P once,
  at its receiver (TCP retransmits it: Zenoh sees delay, not loss);
- bandwidth: a ``tbf`` root qdisc on each host's ``eth0`` (egress);
- partition: the hub end of a host's veth set down (the host keeps its address and
  its sockets, and just stops hearing anything, as with a pulled cable);
- delay: not in this kernel (no ``netem``, and ``tbf`` delays only under load): the
  processes' own receive-side fault layer does it (``--net-delay-ms``, see
  :mod:`tagswarm.protocol.netfaults`), see :mod:`tagswarm.deploy.multihost`.

Everything here builds ``ip`` / ``tc`` / ``iptables`` command lines (pure, tested without
root); :class:`Network` runs them and undoes them whatever happens.
"""

from __future__ import annotations

import logging
import os
import re
import subprocess
import threading
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass

from tagswarm.protocol.errors import TagswarmError

log = logging.getLogger("tagswarm.netns")

SUBNET = "10.77.0"
PREFIX_LEN = 24
BRIDGE = "br0"
HOST_IF = "eth0"
HUB = "hub"
#: a namespace this harness made: tsw<owner pid>x<counter>-<host>
NAME_RE = re.compile(r"^(tsw(\d+)x\d+)-[a-z0-9]+$")
MAX_HOSTS = 250
_counter = iter(range(1, 1 << 30))
_counter_lock = threading.Lock()


class NetnsError(TagswarmError, RuntimeError):
    """A namespace command failed (the message names the command and ip's error)."""


@dataclass(frozen=True)
class Host:
    """One simulated machine: its namespace, its address, and its veth end in the hub."""

    name: str
    ns: str
    addr: str
    hub_if: str


@dataclass(frozen=True)
class Links:
    """Impairment of every host's link: ``loss`` share (0..1) of packets dropped at each
    receiver, ``rate_mbit`` egress bandwidth per host (None: unlimited)."""

    loss: float = 0.0
    rate_mbit: float | None = None

    def __post_init__(self) -> None:
        if not 0.0 <= self.loss < 1.0:
            raise ValueError(f"loss {self.loss!r} must be a share in [0, 1)")
        if self.rate_mbit is not None and not self.rate_mbit > 0:
            raise ValueError(f"rate {self.rate_mbit!r} Mbit/s must be > 0")


@dataclass(frozen=True)
class Topology:
    """The hosts of one run (the first is the router's host) and the hub namespace."""

    prefix: str
    hosts: tuple[Host, ...]

    @property
    def hub(self) -> str:
        return f"{self.prefix}-{HUB}"

    @property
    def namespaces(self) -> tuple[str, ...]:
        return (self.hub, *(h.ns for h in self.hosts))

    def host(self, name: str) -> Host:
        for h in self.hosts:
            if h.name == name:
                return h
        raise KeyError(f"no host {name!r} (hosts: {', '.join(h.name for h in self.hosts)})")


def new_prefix(pid: int | None = None) -> str:
    """A prefix unique on this machine while this process lives: ``tsw<pid>x<n>``."""
    with _counter_lock:
        n = next(_counter)
    return f"tsw{os.getpid() if pid is None else pid}x{n}"


def plan(prefix: str, names: Sequence[str]) -> Topology:
    """The topology for host ``names`` (lower-case letters and digits, unique); addresses
    ``10.77.0.1`` upward in that order."""
    if not re.fullmatch(r"tsw\d+x\d+", prefix):
        raise ValueError(f"prefix {prefix!r} must look like tsw<pid>x<n>")
    if not 1 <= len(names) <= MAX_HOSTS:
        raise ValueError(f"{len(names)} hosts: must be 1..{MAX_HOSTS}")
    if len(set(names)) != len(names):
        raise ValueError(f"host names must be unique: {list(names)}")
    hosts = []
    for i, name in enumerate(names, start=1):
        if not re.fullmatch(r"[a-z][a-z0-9]{0,11}", name) or name == HUB:
            raise ValueError(f"host name {name!r}: 1-12 lower-case letters and digits, not {HUB!r}")
        hosts.append(Host(name=name, ns=f"{prefix}-{name}", addr=f"{SUBNET}.{i}", hub_if=f"v{i}"))
    return Topology(prefix=prefix, hosts=tuple(hosts))


def setup_commands(topo: Topology, links: Links = Links()) -> list[list[str]]:
    """Commands creating the namespaces, the bridge, one veth pair and address per host, and
    the impairments, in order (each must succeed)."""
    hub = topo.hub
    cmds = [["ip", "netns", "add", ns] for ns in topo.namespaces]
    cmds += [["ip", "-n", hub, "link", "add", BRIDGE, "type", "bridge"],
             ["ip", "-n", hub, "link", "set", BRIDGE, "up"],
             ["ip", "-n", hub, "link", "set", "lo", "up"]]
    for h in topo.hosts:
        # created in the hub with its peer straight in the host: never a name in the machine's namespace
        cmds += [["ip", "-n", hub, "link", "add", h.hub_if, "type", "veth", "peer", "name", HOST_IF, "netns", h.ns],
                 ["ip", "-n", hub, "link", "set", h.hub_if, "master", BRIDGE],
                 ["ip", "-n", hub, "link", "set", h.hub_if, "up"],
                 ["ip", "-n", h.ns, "addr", "add", f"{h.addr}/{PREFIX_LEN}", "dev", HOST_IF],
                 ["ip", "-n", h.ns, "link", "set", HOST_IF, "up"],
                 ["ip", "-n", h.ns, "link", "set", "lo", "up"]]
        cmds += impair_commands(h, links)
    return cmds


def impair_commands(host: Host, links: Links) -> list[list[str]]:
    """Loss (iptables statistic, on what ``host`` receives over its link) and bandwidth (tbf on its egress)."""
    cmds: list[list[str]] = []
    if links.loss > 0:
        cmds.append(["ip", "netns", "exec", host.ns, "iptables", "-w", "-A", "INPUT", "-i", HOST_IF, "-m",
                     "statistic", "--mode", "random", "--probability", f"{links.loss:.6f}", "-j", "DROP"])
    if links.rate_mbit is not None:
        # burst: 10 ms of the rate, and never below 32 KB: veth hands tbf segmentation-offloaded packets
        # of up to 64 KB, and a burst under the MTU would drop every full-size packet
        burst_kbit = max(256, int(links.rate_mbit * 1000 * 0.01))
        cmds.append(["ip", "netns", "exec", host.ns, "tc", "qdisc", "replace", "dev", HOST_IF, "root", "tbf",
                     "rate", f"{links.rate_mbit:g}mbit", "burst", f"{burst_kbit}kbit", "latency", "100ms"])
    return cmds


def partition_command(topo: Topology, host: str) -> list[str]:
    """Cut ``host`` off (the hub end of its veth down: the host keeps its address and sockets)."""
    return ["ip", "-n", topo.hub, "link", "set", topo.host(host).hub_if, "down"]


def heal_command(topo: Topology, host: str) -> list[str]:
    """Undo :func:`partition_command`."""
    return ["ip", "-n", topo.hub, "link", "set", topo.host(host).hub_if, "up"]


def exec_argv(host: Host, argv: Sequence[str]) -> list[str]:
    """``argv`` run inside ``host``'s namespace (``ip netns exec`` execs it: same pid)."""
    return ["ip", "netns", "exec", host.ns, *argv]


def teardown_commands(namespaces: Iterable[str]) -> list[list[str]]:
    """Commands removing ``namespaces``: deleting a namespace destroys its veth ends (and so
    their peers), its bridge, addresses, qdiscs and iptables rules."""
    return [["ip", "netns", "delete", ns] for ns in namespaces]


def ours(listing: str, prefix: str) -> list[str]:
    """The namespaces of ``prefix`` in ``ip netns list`` output."""
    return [ns for ns in _names(listing) if ns.startswith(prefix + "-")]


def stale_prefixes(listing: str, alive: Callable[[int], bool]) -> dict[str, list[str]]:
    """Namespaces of this harness (by prefix) whose owner pid is no longer alive: left behind by
    an owner that was SIGKILLed.  ``listing`` is ``ip netns list`` output."""
    out: dict[str, list[str]] = {}
    for ns in _names(listing):
        m = NAME_RE.match(ns)
        if m and not alive(int(m.group(2))):
            out.setdefault(m.group(1), []).append(ns)
    return out


def _names(listing: str) -> list[str]:
    # `ip netns list` prints "name" or "name (id: 3)"
    return [line.split()[0] for line in listing.splitlines() if line.strip()]


def pid_alive(pid: int) -> bool:
    """Whether process ``pid`` exists."""
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def run(cmd: Sequence[str]) -> str:
    """Run one command; its stdout, or :class:`NetnsError` with its stderr."""
    try:
        done = subprocess.run(list(cmd), capture_output=True, text=True, timeout=30, check=False)
    except (OSError, subprocess.TimeoutExpired) as exc:
        raise NetnsError(f"{' '.join(cmd)}: {exc}") from None
    if done.returncode != 0:
        raise NetnsError(f"{' '.join(cmd)}: {done.stderr.strip() or f'exit {done.returncode}'}")
    return done.stdout


def check_available() -> str | None:
    """Why namespaces cannot be made here (not root, no ``ip``), or None."""
    if os.geteuid() != 0:
        return "network namespaces need root (ip netns add)"
    try:
        run(["ip", "netns", "list"])
    except NetnsError as exc:
        return f"no usable `ip netns`: {exc}"
    return None


class Network:
    """The namespaces of a :class:`Topology`, made on enter and deleted on exit (also after an
    error half-way); stale namespaces of dead owners are removed first."""

    def __init__(self, topo: Topology, links: Links = Links()) -> None:
        self.topo, self.links = topo, links
        self.partitioned: set[str] = set()

    def __enter__(self) -> Network:
        for prefix, names in stale_prefixes(run(["ip", "netns", "list"]), pid_alive).items():
            log.warning("removing %d namespaces left by a dead run %s", len(names), prefix)
            self._delete(names)
        try:
            for cmd in setup_commands(self.topo, self.links):
                run(cmd)
        except BaseException:
            self.close()
            raise
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def partition(self, host: str) -> None:
        """Cut ``host`` off from every other host."""
        run(partition_command(self.topo, host))
        self.partitioned.add(host)

    def heal(self, host: str) -> None:
        """Reconnect ``host``."""
        run(heal_command(self.topo, host))
        self.partitioned.discard(host)

    def exec_argv(self, host: str, argv: Sequence[str]) -> list[str]:
        """``argv`` to run on ``host``."""
        return exec_argv(self.topo.host(host), argv)

    def left(self) -> list[str]:
        """Namespaces of this topology that still exist."""
        return ours(run(["ip", "netns", "list"]), self.topo.prefix)

    def close(self) -> None:
        """Delete every namespace of the topology (idempotent)."""
        self._delete(self.left())

    @staticmethod
    def _delete(names: Iterable[str]) -> None:
        for cmd in teardown_commands(names):
            try:
                run(cmd)
            except NetnsError as exc:
                log.warning("%s", exc)

"""A swarm across separate network stacks: every process on a "host" of its own (a Linux
network namespace, tagswarm/deploy/netns.py), joined through a bridge and the router, with
partitions, a router restart, loss and delay (tagswarm/deploy/multihost.py).

Needs root and ``ip netns``: skipped otherwise, except under CI=true, where it fails.
Partitions, the router restart and the lossy run use the realtime clock, as a
deployment on several machines does; the byte-identity check uses lockstep.  Times
asserted are the issue's (lease + 1 s to notice a cut-off agent, 10 s to be localised
again); the measured ones are printed and written beside the run folders.
"""

from __future__ import annotations

import json
import os
import re
import signal
import subprocess
import sys
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest

from tagswarm.deploy import netns
from tagswarm.deploy.hostprobe import Probe
from tagswarm.deploy.multihost import MultiHost
from tagswarm.protocol import codec
from tagswarm.protocol import messages as m
from tagswarm.protocol.bus import DEFAULT_LEASE_MS
from tagswarm.protocol.scenario import load_scenario
from tagswarm.runtime import procgroup

ROOT = Path(__file__).resolve().parents[2]
TAGSWARM = str(Path(sys.executable).parent / "tagswarm")
ROBOTS = (0, 1, 2)
LOCALISED_M = 0.10
LEASE_S = DEFAULT_LEASE_MS / 1000


def _require_netns() -> None:
    why = netns.check_available()
    if why is None:
        return
    if os.environ.get("CI") == "true":
        pytest.fail(f"multi-host tests must run under CI: {why}")
    pytest.skip(why)


def _root_links() -> set[str]:
    """Interface names of the machine's own namespace."""
    out = subprocess.run(["ip", "-o", "link", "show"], capture_output=True, text=True, check=True).stdout
    return {line.split(":")[1].strip().split("@")[0] for line in out.splitlines() if ":" in line}


def _ours(names: set[str]) -> set[str]:
    return {n for n in names if re.fullmatch(r"v\d+|br0", n)}


Make = Callable[..., MultiHost]


@pytest.fixture
def hosts(tmp_path: Path) -> Iterator[Make]:
    """Make a :class:`MultiHost` (entered: namespaces up); every one is closed at the end, and
    the test fails if a namespace, an interface or a process of it is left."""
    _require_netns()
    made: list[MultiHost] = []
    before = _root_links()

    def make(clock: str, duration_s: float, **kw: Any) -> MultiHost:
        scen = load_scenario("paper", [f'clock.mode="{clock}"', f"robots.count={len(ROBOTS)}",
                                       f"duration_s={duration_s}", "seed=0"])
        mh = MultiHost(tmp_path / f"run{len(made)}", scen, **kw)
        made.append(mh)
        mh.__enter__()
        return mh

    try:
        yield make
    finally:
        for mh in made:
            mh.close()
    for mh in made:
        assert mh.net.left() == [], mh.net.left()
        assert not [c.name for c in mh.children.values() if procgroup.group_alive(c.pgid)]
    assert _ours(_root_links()) - _ours(before) == set()


def _localised(mh: MultiHost, rid: int, after_sim_s: float = 0.0) -> bool:
    """A correction for ``rid`` stamped after ``after_sim_s``, within LOCALISED_M of the truth."""
    p = mh.probe
    assert p is not None
    fused = p.rec.fused.get(rid)
    err = p.rec.fused_error(rid)
    return fused is not None and bool(fused) and fused[-1][0] > after_sim_s * 1e9 and err is not None \
        and err < LOCALISED_M


def _localised_swarm(hosts: Make, duration_s: float) -> tuple[MultiHost, Probe]:
    """A realtime swarm across the hosts, started and run until every robot is localised (>= 4 s)."""
    mh = hosts("realtime", duration_s, report=False)
    mh.start()
    p = mh.probe
    assert p is not None
    mh.until(lambda: p.sim_s() >= 4.0 and all(_localised(mh, r) for r in ROBOTS), 120,
             "the swarm never got localised")
    return mh, p


def _all_exited_0(codes: dict[str, int | None]) -> None:
    assert {n: c for n, c in codes.items() if n != "router"} == {n: 0 for n in codes if n != "router"}, codes


def _report(mh: MultiHost, name: str, numbers: dict[str, Any]) -> None:
    print(name, json.dumps(numbers))
    (mh.out / f"{name}.json").write_text(json.dumps(numbers, indent=1))


def test_lockstep_across_hosts_is_byte_identical_to_one_host(hosts: Make, tmp_path: Path) -> None:
    mh = hosts("lockstep", 6.0, report=False)
    mh.start()
    mh.until(lambda: mh.alive("world/0"), 60, "the world never came up")  # past `ip netns exec`'s setns
    # every process in its own network stack (router and recorder share the router's host)
    stacks = {name: os.readlink(f"/proc/{c.pid}/ns/net") for name, c in mh.children.items()}
    assert stacks["router"] == stacks["recorder"]
    assert len(set(stacks.values())) == len(stacks) - 1 and os.readlink("/proc/self/ns/net") not in stacks.values()
    _all_exited_0(mh.wait_end(240))
    one = tmp_path / "onehost"
    subprocess.run([TAGSWARM, "up", "--clock", "lockstep", "--robots", str(len(ROBOTS)), "--seed", "0",
                    "--duration", "6", "--out", str(one), "--no-live", "--no-report"],
                   check=True, timeout=240, stdout=subprocess.DEVNULL, stderr=subprocess.STDOUT)
    for rid in ROBOTS:
        for kind in ("truth", "odom", "fused"):
            across = (mh.out / "trajectories" / f"{kind}_{rid}.tum").read_bytes()
            alone = (one / "trajectories" / f"{kind}_{rid}.tum").read_bytes()
            assert across.count(b"\n") > 100, (kind, rid)
            assert across == alone, f"{kind}_{rid}.tum differs between several hosts and one"


def test_agent_host_partitioned_is_dropped_stops_and_rejoins(hosts: Make) -> None:
    victim = 2
    # the run must outlast the heal by the 10 s the agent is given to come back: placed at ~5 s, cut, noticed
    # within the lease, healed 5 s after the cut, a 20 s run ended 9 s after the heal, and on a loaded CI machine
    # the agent had not reconnected by then ("never came back localised", 2026-12-07)
    mh, p = _localised_swarm(hosts, 30.0)
    bus = mh.bus
    assert bus is not None
    asked_at = [0.0]
    answer: list[bool | None] = [None]

    def server_says_alive() -> bool | None:
        if time.monotonic() - asked_at[0] >= 0.1:  # the server's own view, from its map queryable
            asked_at[0], answer[0] = time.monotonic(), None
            for reply in bus.get(mh.keys.map(), timeout_s=0.5):
                gmap = codec.decode(m.GlobalMap, reply.value)
                answer[0] = next((e.alive for e in gmap.robots if e.robot_id == victim), None)
        return answer[0]

    t_cut, sim_cut = p.now(), p.sim_s()
    mh.partition(f"agent{victim}")
    seen: dict[str, float] = {}

    def noticed() -> bool:
        if server_says_alive() is False:
            seen["server_s"] = p.now() - t_cut
        return "server_s" in seen

    # the server's mark is what counts: its token may outlive the cut by up to Zenoh's 10 s TCP linger
    # when the router holds unsent bytes for it (tagswarm/runtime/presence.py), so the server also
    # calls an agent gone once its odometry stops; when the token went is only reported
    mh.until(noticed, 30, "the cut-off agent was never marked not alive")
    mh.until(lambda: p.now() - t_cut >= 5.0, 30, "")
    sim_heal, t_heal = p.sim_s(), p.now()
    mh.heal(f"agent{victim}")
    mh.until(lambda: mh.alive(f"agent/{victim}") and _localised(mh, victim, sim_heal), 60,
             "the agent never came back localised")
    back_sim_s, back_wall_s = p.sim_s() - sim_heal, p.now() - t_heal
    # its robot stood still from a command timeout after the cut (the world heard no command) to the heal;
    # the others went on: the patrolling robot 1 moved meanwhile
    def moved(rid: int) -> float:
        pts = [q for t, q in p.rec.truth[rid] if (sim_cut + 1.0) * 1e9 <= t <= sim_heal * 1e9]
        assert len(pts) > 30, (rid, len(pts))
        return max(abs(a[0] - pts[0][0]) + abs(a[1] - pts[0][1]) for a in pts)

    victim_moved, other_moved = moved(victim), moved(1)
    gone = p.went(f"agent/{victim}", False, t_cut)
    if gone is not None:
        seen["token_gone_s"] = gone - t_cut
    codes = mh.wait_end(120)
    _report(mh, "agent_partition", {**seen, "lease_s": LEASE_S, "sim_cut_s": sim_cut, "sim_heal_s": sim_heal,
                                    "localised_again_sim_s": back_sim_s, "localised_again_wall_s": back_wall_s,
                                    "victim_moved_m": victim_moved, "robot1_moved_m": other_moved})
    assert seen["server_s"] <= LEASE_S + 1.0, seen
    assert victim_moved < 0.01, victim_moved
    assert other_moved > 0.05, other_moved
    assert back_sim_s <= 10.0, back_sim_s
    _all_exited_0(codes)


def test_server_host_partitioned_agents_run_on_odometry_then_recover(hosts: Make) -> None:
    # recovery usually takes 1-3 s, but the server's old TCP link can hold its socket's close for
    # Zenoh's fixed 10 s SO_LINGER (see tagswarm.runtime.presence): the run must outlast that after
    # the heal, or a slow CI machine ends it first (seen once: the run ended 7.6 s after the heal)
    mh, p = _localised_swarm(hosts, 30.0)
    sim_cut, t_cut = p.sim_s(), p.now()
    mh.partition("server")

    def on_odometry() -> bool:
        return all(p.rec.mode_now.get(r) == "odometry" and p.rec.counters.get(f"agent/{r}", {}).get("server_alive") == 0
                   for r in ROBOTS)

    mh.until(on_odometry, 30, "the agents never fell back to odometry")
    mh.until(lambda: p.now() - t_cut >= 4.0, 30, "")
    # they kept dead-reckoning through the outage
    for r in ROBOTS:
        assert p.rec.odom[r][-1][0] > (sim_cut + 1.0) * 1e9, r
    sim_heal = p.sim_s()
    mh.heal("server")

    def recovered() -> bool:
        return all(p.rec.mode_now.get(r) != "odometry" and p.rec.counters.get(f"agent/{r}", {}).get("server_alive") == 1
                   and _localised(mh, r, sim_heal) for r in ROBOTS)

    took = mh.until(recovered, 60, "the agents never took corrections again")
    codes = mh.wait_end(120)
    _report(mh, "server_partition", {"sim_cut_s": sim_cut, "sim_heal_s": sim_heal, "recovered_wall_s": took})
    _all_exited_0(codes)


def test_router_restarted_everyone_reconnects_and_the_run_goes_on(hosts: Make) -> None:
    mh, p = _localised_swarm(hosts, 14.0)
    everyone = ["router/0", "recorder/0", "world/0", "server/0", *(f"agent/{r}" for r in ROBOTS)]
    t_restart, sim_restart = p.now(), p.sim_s()
    mh.restart("router")
    took = mh.until(lambda: all(mh.alive(w) for w in everyone) and p.sim_s() >= sim_restart + 3.0
                    and all(_localised(mh, r, sim_restart + 1.0) for r in ROBOTS), 90,
                    "the swarm did not come back after the router restart")
    assert p.went("world/0", False, t_restart) is not None  # it really was cut off
    codes = mh.wait_end(120)
    _report(mh, "router_restart", {"back_wall_s": took, "sim_restart_s": sim_restart})
    _all_exited_0(codes)
    assert mh.restarts["router"] == 2
    truth = (mh.out / "trajectories" / "truth_1.tum").read_text().splitlines()
    assert float(truth[-1].split()[0]) >= 13.0  # the recorder, reconnected too, has the run to its end


def test_realtime_with_20_5_ms_delay_and_5_percent_loss_completes_localised(hosts: Make) -> None:
    delay_ms, jitter_ms = 20.0, 5.0  # every message 15..25 ms late (seeded), each key in order
    mh = hosts("realtime", 12.0, delay_ms=delay_ms, jitter_ms=jitter_ms, loss=0.05, latency=True, report=True)
    mh.start()
    codes = mh.wait_end(240)
    # the kernel dropped packets on the links (iptables statistic)
    rules = subprocess.run(mh.net.exec_argv("agent1", ["iptables", "-w", "-L", "INPUT", "-v", "-n", "-x"]),
                           capture_output=True, text=True, check=True).stdout
    dropped = sum(int(line.split()[0]) for line in rules.splitlines() if "statistic" in line)
    _all_exited_0(codes)
    metrics = json.loads((mh.out / "metrics.json").read_text())
    summary = json.loads((mh.out / "multihost.json").read_text())
    lat = summary["probe"]["latency_image_to_correction_ms"]
    localised = {r: metrics["robots"][str(r)]["fused"]["time_localised"] for r in ROBOTS}
    _report(mh, "lossy", {"dropped_packets_agent1": dropped, "latency_ms": lat, "rtf": summary["probe"]["rtf"],
                          "time_localised": localised})
    assert dropped > 0
    assert mh.probe is not None
    for r in ROBOTS:
        err = mh.probe.rec.fused_error(r)
        assert err is not None and err < LOCALISED_M, (r, err)
        assert localised[r] > 0.5, localised
    # image -> correction crosses at least two delayed receptions (agent, then server)
    assert lat["n"] > 10 and lat["p50"] >= 2 * (delay_ms - jitter_ms), lat
    argv = summary["commands"]["agent/1"]["argv"]
    assert argv[argv.index("--net-jitter-ms") + 1] == "5" and summary["links"]["jitter_ms"] == jitter_ms


def _wait_file_has(path: Path, text: str, proc: subprocess.Popen[bytes], timeout_s: float) -> None:
    deadline = time.monotonic() + timeout_s
    while not (path.exists() and text in path.read_text(errors="replace")):
        assert proc.poll() is None, f"multihost.sh exited {proc.returncode} early"
        assert time.monotonic() < deadline, f"{path} never said {text!r}"
        time.sleep(0.2)


def _processes_mentioning(text: str) -> list[int]:
    out = []
    for pid in os.listdir("/proc"):
        try:
            if pid.isdigit() and text.encode() in Path(f"/proc/{pid}/cmdline").read_bytes():
                out.append(int(pid))
        except OSError:
            pass
    return out


@pytest.mark.parametrize("how", ["ctrl-c", "crash"])
def test_script_leaves_no_namespace_veth_or_process(tmp_path: Path, how: str) -> None:
    _require_netns()
    before = _root_links()
    out = tmp_path / "run"
    proc = subprocess.Popen(["bash", str(ROOT / "scripts" / "multihost.sh"), "--out", str(out), "--robots", "1",
                             "--clock", "lockstep", "--duration", "600", "--seed", "0", "--no-report"],
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True,
                            env=dict(os.environ, TAGSWARM_PYTHON=sys.executable))
    prefix = f"tsw{proc.pid}x1"  # the script execs python: same pid
    try:
        _wait_file_has(out / "logs" / "world.log", "lockstep clock", proc, 120)
        listing = subprocess.run(["ip", "netns", "list"], capture_output=True, text=True, check=True).stdout
        assert len(netns.ours(listing, prefix)) == 5  # hub, router, world, server, agent0
        if how == "ctrl-c":
            proc.send_signal(signal.SIGINT)
        else:  # the world host's processes die: the harness fails and tears down
            pids = subprocess.run(["ip", "netns", "pids", f"{prefix}-world"], capture_output=True, text=True,
                                  check=True).stdout.split()
            assert pids
            for pid in pids:
                os.kill(int(pid), signal.SIGKILL)
        code = proc.wait(120)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
    listing = subprocess.run(["ip", "netns", "list"], capture_output=True, text=True, check=True).stdout
    assert netns.ours(listing, prefix) == []
    assert _ours(_root_links()) - _ours(before) == set()
    deadline = time.monotonic() + 10  # the reaper's last SIGKILLs may still be landing
    while _processes_mentioning(str(out)) and time.monotonic() < deadline:
        time.sleep(0.1)
    assert _processes_mentioning(str(out)) == []
    if how == "ctrl-c":
        assert code == 130
        assert (out / "run.json").exists()  # the recorder wrote what it had
    else:
        assert code == 1

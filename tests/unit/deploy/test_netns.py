"""The multi-host harness's command lines, built without root (tagswarm/deploy/netns.py, hostplan.py, multihost.py)."""

from __future__ import annotations

from pathlib import Path

import pytest

from tagswarm.deploy import hostplan, multihost, netns
from tagswarm.protocol.scenario import load_scenario


def topo(robots: int = 2) -> netns.Topology:
    return netns.plan("tsw42x1", hostplan.host_names(list(range(robots))))


def test_plan_gives_each_host_its_namespace_address_and_hub_port() -> None:
    t = topo(2)
    assert [h.name for h in t.hosts] == ["router", "world", "server", "agent0", "agent1"]
    assert [h.addr for h in t.hosts] == ["10.77.0.1", "10.77.0.2", "10.77.0.3", "10.77.0.4", "10.77.0.5"]
    assert t.host("agent1").ns == "tsw42x1-agent1"
    assert t.host("agent1").hub_if == "v5"
    assert t.hub == "tsw42x1-hub"
    assert t.namespaces[0] == "tsw42x1-hub" and len(t.namespaces) == 6
    assert all(len(h.hub_if) <= 15 for h in t.hosts)  # Linux interface names


@pytest.mark.parametrize("prefix, names", [("x1", ["a"]), ("tsw1x1", []), ("tsw1x1", ["a", "a"]),
                                           ("tsw1x1", ["Agent"]), ("tsw1x1", ["hub"]), ("tsw1x1", ["a-b"])])
def test_plan_refuses_bad_names(prefix: str, names: list[str]) -> None:
    with pytest.raises(ValueError):
        netns.plan(prefix, names)


def test_new_prefixes_are_unique_and_carry_the_pid() -> None:
    a, b = netns.new_prefix(123), netns.new_prefix(123)
    assert a != b and a.startswith("tsw123x") and b.startswith("tsw123x")


def test_setup_never_touches_the_machines_own_namespace() -> None:
    cmds = netns.setup_commands(topo(1), netns.Links(loss=0.05, rate_mbit=100))
    for cmd in cmds:
        in_ns = cmd[:2] == ["ip", "-n"] or cmd[:3] in (["ip", "netns", "add"], ["ip", "netns", "exec"])
        assert in_ns, cmd
    veth = [c for c in cmds if "veth" in c]
    assert veth == [["ip", "-n", "tsw42x1-hub", "link", "add", f"v{i}", "type", "veth", "peer", "name", "eth0",
                     "netns", ns] for i, ns in enumerate(["tsw42x1-router", "tsw42x1-world", "tsw42x1-server",
                                                          "tsw42x1-agent0"], start=1)]
    assert ["ip", "-n", "tsw42x1-agent0", "addr", "add", "10.77.0.4/24", "dev", "eth0"] in cmds


def test_loss_is_an_iptables_statistic_drop_and_rate_a_tbf() -> None:
    h = topo(1).host("agent0")
    cmds = netns.impair_commands(h, netns.Links(loss=0.05, rate_mbit=10))
    assert cmds[0] == ["ip", "netns", "exec", "tsw42x1-agent0", "iptables", "-w", "-A", "INPUT", "-i", "eth0", "-m",
                       "statistic", "--mode", "random", "--probability", "0.050000", "-j", "DROP"]
    assert cmds[1][:9] == ["ip", "netns", "exec", "tsw42x1-agent0", "tc", "qdisc", "replace", "dev", "eth0"]
    assert cmds[1][9:13] == ["root", "tbf", "rate", "10mbit"]
    assert netns.impair_commands(h, netns.Links()) == []


@pytest.mark.parametrize("loss, rate", [(-0.1, None), (1.0, None), (0.0, 0.0)])
def test_links_refuse_bad_values(loss: float, rate: float | None) -> None:
    with pytest.raises(ValueError):
        netns.Links(loss=loss, rate_mbit=rate)


def test_partition_downs_the_hub_end_and_heal_raises_it() -> None:
    t = topo(1)
    assert netns.partition_command(t, "server") == ["ip", "-n", "tsw42x1-hub", "link", "set", "v3", "down"]
    assert netns.heal_command(t, "server") == ["ip", "-n", "tsw42x1-hub", "link", "set", "v3", "up"]
    with pytest.raises(KeyError):
        netns.partition_command(t, "nowhere")


def test_stale_namespaces_are_those_of_dead_owners_only() -> None:
    listing = "tsw10x1-hub (id: 3)\ntsw10x1-router\ntsw11x2-hub\nmy-own-ns\ntsw10x1\n"
    stale = netns.stale_prefixes(listing, alive=lambda pid: pid == 11)
    assert stale == {"tsw10x1": ["tsw10x1-hub", "tsw10x1-router"]}
    assert netns.ours(listing, "tsw11x2") == ["tsw11x2-hub"]
    assert netns.teardown_commands(["tsw10x1-hub"]) == [["ip", "netns", "delete", "tsw10x1-hub"]]


def test_every_process_is_a_client_of_the_router_on_its_own_host(tmp_path: Path) -> None:
    t = topo(2)
    cmds = hostplan.commands(t, run="r1", scenario_file=tmp_path / "s.json", out=tmp_path, robots=[0, 1],
                              delay_ms=20, lease_ms=1500)
    assert {n: h for n, (h, _) in cmds.items()} == {"router": "router", "recorder": "router", "server": "server",
                                                    "agent/0": "agent0", "agent/1": "agent1", "world": "world"}
    router = cmds["router"][1]
    assert router[:4] == ["tagswarm", "router", "--listen", "tcp/0.0.0.0:7447"]
    for name in ("recorder", "server", "agent/0", "world"):
        argv = cmds[name][1]
        i = argv.index("--connect")
        assert argv[i - 2: i + 2] == ["--zenoh-mode", "client", "--connect", "tcp/10.77.0.1:7447"], name
        assert argv[argv.index("--run") + 1] == "r1" and "--zenoh-lease-ms" in argv
    # delay on every key of the run, in the swarm's processes, never in the router or the recorder
    for name in ("server", "agent/1", "world"):
        argv = cmds[name][1]
        assert argv[argv.index("--net-delay-ms") + 1] == "20"
        assert argv[argv.index("--net-fault-keys") + 1] == "tagswarm/r1/**"
    assert "--net-delay-ms" not in router and "--net-delay-ms" not in cmds["recorder"][1]
    assert cmds["agent/1"][1][:4] == ["tagswarm", "agent", "--robot-id", "1"]
    assert cmds["recorder"][1][:4] == ["tagswarm", "record-run", "--out", str(tmp_path)]
    no_delay = hostplan.commands(t, run="r1", scenario_file=tmp_path / "s.json", out=tmp_path, robots=[0, 1])
    assert all("--net-delay-ms" not in argv and "--zenoh-lease-ms" not in argv for _, argv in no_delay.values())


def test_the_scenario_is_resolved_as_compose_resolves_it() -> None:
    scen = hostplan.resolve(load_scenario("paper", ["robots.count=3", 'clock.mode="lockstep"']))
    assert list(scen.clock.participants) == ["agent/0", "agent/1", "agent/2", "server/0"]
    assert "recorder/0" in scen.clock.observers


def test_the_router_closes_a_blocked_link_well_within_a_lease() -> None:
    assert "wait_before_close: 500000" in hostplan.ROUTER_CONFIG  # microseconds: 0.5 s < the 1.5 s lease


def test_bad_flags_exit_2_with_one_line(capsys: pytest.CaptureFixture[str], tmp_path: Path) -> None:
    assert multihost.main(["--out", str(tmp_path), "--loss", "1.5"]) == 2
    assert multihost.main(["--out", str(tmp_path), "--delay-ms", "-1"]) == 2
    lines = capsys.readouterr().err.strip().splitlines()
    assert lines == ["tagswarm multihost: error: --loss 1.5: must be a share in [0, 1)",
                     "tagswarm multihost: error: --delay-ms -1: must be 0..60000"]
    with pytest.raises(SystemExit) as exc:
        multihost.main(["--loss", "0.1"])  # no --out
    assert exc.value.code == 2


def test_help_explains_the_link_flags(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as exc:
        multihost.main(["--help"])
    assert exc.value.code == 0
    text = capsys.readouterr().out
    for flag in ("--out", "--delay-ms", "--loss", "--rate-mbit", "--robots", "--clock", "--duration"):
        assert flag in text, flag
    assert "10.77.0" in text and "network namespaces" in text


def test_a_delay_spread_gives_each_host_its_own_seeded_delay(tmp_path: Path) -> None:
    t = topo(3)
    cmds = hostplan.commands(t, run="r1", scenario_file=tmp_path / "s.json", out=tmp_path, robots=[0, 1, 2],
                             delay_ms=20, spread_ms=5, seed=7)
    delays = {n: float(argv[argv.index("--net-delay-ms") + 1]) for n, (_, argv) in cmds.items() if n != "router"
              and n != "recorder"}
    assert all(15.0 <= d <= 25.0 for d in delays.values()), delays
    assert len(set(delays.values())) == len(delays)  # links differ
    again = hostplan.commands(t, run="r1", scenario_file=tmp_path / "s.json", out=tmp_path, robots=[0, 1, 2],
                              delay_ms=20, spread_ms=5, seed=7)
    assert again == cmds
    assert hostplan.host_delay_ms("agent0", 20, 0, 7) == 20
    assert hostplan.host_delay_ms("agent0", 1, 5, 7) >= 0


def test_jitter_goes_to_every_delayed_process(tmp_path: Path) -> None:
    cmds = hostplan.commands(topo(2), run="r1", scenario_file=tmp_path / "s.json", out=tmp_path, robots=[0, 1],
                             delay_ms=20, jitter_ms=5)
    for name, (_, argv) in cmds.items():
        if name in ("router", "recorder"):
            assert "--net-jitter-ms" not in argv
        else:
            assert argv[argv.index("--net-jitter-ms") + 1] == "5", name
    none = hostplan.commands(topo(2), run="r1", scenario_file=tmp_path / "s.json", out=tmp_path, robots=[0, 1],
                             delay_ms=20)
    assert all("--net-jitter-ms" not in argv for _, argv in none.values())

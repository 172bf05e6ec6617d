"""tagswarm.testing.options: overrides written as TOML the scenario loader reads back, the fault
flags the processes parse, per-process extras, and one-line errors for bad arguments."""

from __future__ import annotations

import math
from pathlib import Path

import pytest

from tagswarm.protocol.scenario import parse_value
from tagswarm.runtime.config import Invocation, OneLineParser, add_common_args
from tagswarm.runtime.process import child_env
from tagswarm.testing.errors import SwarmError
from tagswarm.testing.options import (
    NetFault,
    SwarmSpec,
    check_name,
    command,
    log_name,
    overrides,
    process_names,
    toml_literal,
)


@pytest.mark.parametrize("value", [True, False, 0, -3, 2.5, 1e-9, "lockstep", 'a "quoted" \\ name', [1, 2.5],
                                   ["x", "y"], {"x_m": 1.0, "y_m": -2}, [{"x_m": 0.5}]])
def test_a_literal_reads_back_as_the_value(value: object) -> None:
    assert parse_value(toml_literal(value)) == value


@pytest.mark.parametrize("bad", [math.nan, math.inf, object(), {"a b": 1}, {1: 2}])
def test_values_toml_cannot_hold_are_refused(bad: object) -> None:
    with pytest.raises(SwarmError):
        toml_literal(bad)


def test_dotted_keys_and_double_underscore_keywords_become_overrides() -> None:
    assert overrides({"agent.avoid": False, "clock.tick_hz": 20}, {"render__workers": 2}) == (
        "agent.avoid=false", "clock.tick_hz=20", "render.workers=2")
    for bad in ("agent..avoid", "agent.avoid=1", "", "a b"):
        with pytest.raises(SwarmError, match="dotted"):
            overrides({bad: 1})


def test_the_spec_builds_a_lockstep_scenario_with_every_agent_and_the_server_acking() -> None:
    spec = SwarmSpec.make(scenario="paper", robots=3, seed=7, duration_s=5, set={"agent.avoid": False})
    s = spec.build_scenario()
    assert (s.seed, s.duration_s, s.robot_ids, s.clock.mode) == (7, 5.0, (0, 1, 2), "lockstep")
    assert s.clock.participants == ("agent/0", "agent/1", "agent/2", "server/0")
    assert s.agent.avoid is False
    assert process_names(s) == ["server", "agent/0", "agent/1", "agent/2", "world"]


def test_none_keeps_the_scenario_values_and_realtime_names_no_participants() -> None:
    s = SwarmSpec.make(seed=None, duration_s=None, clock="realtime").build_scenario()
    assert (s.seed, s.duration_s, s.robot_ids, s.clock.participants) == (0, 60.0, (0, 1, 2, 3), ())


@pytest.mark.parametrize("kwargs", [{"clock": "fast"}, {"robots": 0}, {"robots": True}, {"duration_s": -1},
                                    {"duration_s": math.inf}, {"agent_modules": {1: ""}},
                                    {"net": {"robot1": NetFault()}}, {"extra_args": {"server": "--lag 3"}}])
def test_bad_arguments_are_refused_up_front(kwargs: dict[str, object]) -> None:
    with pytest.raises(SwarmError):
        SwarmSpec.make(**kwargs)  # type: ignore[arg-type]


def test_names_outside_the_run_are_refused_when_the_scenario_is_known() -> None:
    with pytest.raises(SwarmError, match="robot 9"):
        SwarmSpec.make(robots=2, agent_modules={9: "pkg.ctl"}).build_scenario()
    with pytest.raises(SwarmError, match="agent/5"):
        SwarmSpec.make(robots=2, extra_args={"agent/5": ["-x"]}).build_scenario()


def test_agent_modules_and_extra_args_land_on_that_process_only() -> None:
    spec = SwarmSpec.make(robots=2, agent_modules={1: "pkg.ctl"}, extra_args={"agent/1": ["--fetch-map-timeout", "2"],
                                                                              "server": ["--lag", "5"]})
    assert spec.extra("agent/1") == ("--fetch-map-timeout", "2", "--agent-module", "pkg.ctl")
    assert spec.extra("agent/0") == ()
    assert spec.extra("server") == ("--lag", "5")
    argv = command("agent/1", ["--run", "r"], spec.extra("agent/1"), bin_dir=Path("/nonexistent"))
    assert argv[1:] == ["-m", "tagswarm.agents.node", "--robot-id", "1", "--run", "r", "--fetch-map-timeout", "2",
                        "--agent-module", "pkg.ctl"]


def test_fault_flags_parse_back_to_the_bus_config() -> None:
    fault = NetFault(loss=0.25, delay_ms=40, keys=("tagswarm/*/robot/*/encoders",), seed=5)
    p = OneLineParser(prog="x")
    add_common_args(p)
    bus = Invocation(p, fault.flags(), environ={}).bus()
    assert (bus.loss, bus.delay_ms, bus.fault_keys, bus.fault_seed) == (0.25, 40.0, ("tagswarm/*/robot/*/encoders",), 5)


def test_a_per_process_fault_wins_over_the_one_for_all() -> None:
    everyone, mine = NetFault(loss=0.1), NetFault(delay_ms=5)
    spec = SwarmSpec.make(net=everyone)
    assert spec.fault("server") == everyone
    spec = SwarmSpec.make(net={"agent/1": mine})
    assert (spec.fault("agent/1"), spec.fault("agent/0")) == (mine, None)
    assert "--net-delay-ms" in command("agent/1", [], (), mine)


@pytest.mark.parametrize("kwargs", [{"loss": 1.5}, {"loss": math.nan}, {"delay_ms": -1}, {"keys": "a/b"},
                                    {"keys": ("a//b",)}])
def test_bad_faults_are_refused(kwargs: dict[str, object]) -> None:
    with pytest.raises(SwarmError):
        NetFault(**kwargs)  # type: ignore[arg-type]


def test_process_names_and_log_names() -> None:
    assert [check_name(n) for n in ("world", "server", "agent/0", "agent/12")]
    for bad in ("agent1", "agent/", "agent/01", "router", "agent/-1"):
        with pytest.raises(SwarmError):
            check_name(bad)
    assert log_name("agent/3") == "agent3"


def test_children_get_no_tagswarm_variables() -> None:
    env = child_env({"PATH": "/bin", "TAGSWARM_RUN": "mine", "TAGSWARM_NET_LOSS": "0.5"})
    assert env == {"PATH": "/bin", "PYTHONUNBUFFERED": "1"}


def test_an_agent_with_the_tests_own_controller_can_import_what_the_test_can(tmp_path: Path) -> None:
    env = child_env({"PYTHONPATH": "/opt/lib"}, import_path=["", str(tmp_path), "/no/such/dir", str(tmp_path)])
    assert env["PYTHONPATH"] == f"/opt/lib:{tmp_path}"
    assert "PYTHONPATH" not in child_env({})
    spec = SwarmSpec.make(robots=2, agent_modules={1: "ctl"})
    assert (spec.agent_module("agent/1"), spec.agent_module("agent/0"), spec.agent_module("world")) == ("ctl", None,
                                                                                                     None)


def test_a_scenario_that_does_not_load_is_a_swarm_error_naming_the_field() -> None:
    from tagswarm.protocol.scenario_schema import ScenarioError
    from tagswarm.testing import SwarmError, SwarmScenarioError

    with pytest.raises(SwarmScenarioError) as exc:
        SwarmSpec.make(robots=2, **{"robot.cameras": [{"width": -1}]}).build_scenario()
    assert isinstance(exc.value, SwarmError) and isinstance(exc.value, ScenarioError)
    assert "robot.cameras[0].width" in str(exc.value)


def test_a_reused_run_is_keyed_by_what_it_resolves_to() -> None:
    # robots=None keeps the paper scenario's own 4 robots: the same run as robots=4, not a second one
    assert SwarmSpec.make(robots=None).same_run_key() == SwarmSpec.make(robots=4).same_run_key()
    assert SwarmSpec.make(seed=0).same_run_key() != SwarmSpec.make(seed=1).same_run_key()
    assert SwarmSpec.make(robots=3).same_run_key() != SwarmSpec.make(robots=4).same_run_key()
    assert SwarmSpec.make(robots=4, agent_modules={1: "ctl"}).same_run_key() != SwarmSpec.make(robots=4).same_run_key()
    assert SwarmSpec.make(set={"agent.max_speed_m_s": 0.1}).same_run_key() != SwarmSpec.make().same_run_key()

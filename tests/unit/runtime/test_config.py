"""Config layering (TOML < TAGSWARM_* environment < CLI flags) through the world's build_config,
and the world's console entry point on bad input.  No Zenoh session is opened: every case
here fails (or finishes) before ``open_bus``."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import pytest

from tagswarm.protocol.bus import DEFAULT_LEASE_MS, zenoh_config
from tagswarm.protocol.keys import KeyNameError
from tagswarm.protocol.scenario import ScenarioError, load_scenario
from tagswarm.runtime.config import ConfigError, env_of
from tagswarm.world import node
from tagswarm.world.config import WorldConfig, build_config, resolve_render_workers

CONFIG_ERRORS = (ConfigError, ScenarioError)


def cfg(argv: Sequence[str] = (), **env: str) -> WorldConfig:
    return build_config(list(argv), env)


# --------------------------------------------------------------------------- defaults


def test_defaults_without_env_or_flags() -> None:
    c = cfg()
    assert c.scenario == resolve_render_workers(load_scenario("paper"))  # the world picks its render workers
    assert c.run == "default"
    assert c.log_level == "INFO"
    assert c.status_period_s == 1.0
    assert c.spawn_render_workers is True
    assert c.bus.mode == "peer"
    assert c.bus.listen == () and c.bus.connect == ()
    assert c.bus.multicast_scouting is False
    assert c.bus.config_file is None


def test_only_tagswarm_variables_count() -> None:
    environ = {"SEED": "3", "tagswarm_seed": "4", "TAGSWARMSEED": "5", "PATH": "/bin", "TAGSWARM_RUN": "r"}
    assert env_of(environ) == {"TAGSWARM_RUN": "r"}
    c = build_config([], environ)
    assert c.scenario.seed == 0
    assert c.run == "r"


# --------------------------------------------------------------------------- precedence


def test_env_seed_beats_toml() -> None:
    assert cfg(TAGSWARM_SEED="5").scenario.seed == 5


def test_cli_seed_beats_env() -> None:
    assert cfg(["--seed", "7"], TAGSWARM_SEED="5").scenario.seed == 7


def test_env_set_applies_every_assignment() -> None:
    s = cfg(TAGSWARM_SET="clock.tick_hz=60;robots.count=2").scenario
    assert s.clock.tick_hz == 60.0
    assert s.robots.count == 2
    assert s.seed == 0


def test_env_set_ignores_empty_items() -> None:
    s = cfg(TAGSWARM_SET=";clock.tick_hz=60; ;robots.count=2;").scenario
    assert (s.clock.tick_hz, s.robots.count) == (60.0, 2)


def test_cli_set_beats_env_set() -> None:
    s = cfg(["--set", "robots.count=3"], TAGSWARM_SET="clock.tick_hz=60;robots.count=2").scenario
    assert s.robots.count == 3
    assert s.clock.tick_hz == 60.0  # the env assignment nobody overrode still applies


def test_repeated_cli_set_last_wins() -> None:
    assert cfg(["--set", "seed=1", "--set", "seed=2"]).scenario.seed == 2


def test_cli_set_beats_env_typed_variable() -> None:
    assert cfg(["--set", "robots.count=1"], TAGSWARM_ROBOTS="2").scenario.robots.count == 1


def test_cli_typed_flag_beats_cli_set() -> None:
    assert cfg(["--set", "seed=1", "--seed", "9"]).scenario.seed == 9


@pytest.mark.parametrize(
    ("env_name", "env_value", "flag", "flag_value", "field", "env_expect", "cli_expect"),
    [
        ("TAGSWARM_ROBOTS", "2", "--robots", "3", ("robots", "count"), 2, 3),
        ("TAGSWARM_CLOCK", "lockstep", "--clock", "realtime", ("clock", "mode"), "lockstep", "realtime"),
        ("TAGSWARM_DURATION", "12.5", "--duration", "3", (None, "duration_s"), 12.5, 3.0),
        ("TAGSWARM_SEED", "11", "--seed", "12", (None, "seed"), 11, 12),
    ],
)
def test_typed_variables_and_flags(env_name: str, env_value: str, flag: str, flag_value: str,
                                   field: tuple[str | None, str], env_expect: object, cli_expect: object) -> None:
    def value(c: WorldConfig) -> object:
        section, attr = field
        obj = c.scenario if section is None else getattr(c.scenario, section)
        return getattr(obj, attr)

    assert value(cfg(**{env_name: env_value})) == env_expect
    assert value(cfg([flag, flag_value], **{env_name: env_value})) == cli_expect
    assert value(cfg([flag, flag_value])) == cli_expect


def test_scenario_from_env_and_cli(tmp_path: Path) -> None:
    path = tmp_path / "two.toml"
    path.write_text('name = "two"\n[robots]\ncount = 2\n')
    assert cfg(TAGSWARM_SCENARIO=str(path)).scenario.name == "two"
    assert cfg(TAGSWARM_SCENARIO=str(path)).scenario.robots.count == 2
    assert cfg(["--scenario", "paper"], TAGSWARM_SCENARIO=str(path)).scenario.name == "paper"
    assert cfg(["--scenario", str(path), "--robots", "3"]).scenario.robots.count == 3


def test_run_log_level_from_env_and_cli() -> None:
    c = cfg(TAGSWARM_RUN="bench-7", TAGSWARM_LOG_LEVEL="DEBUG")
    assert (c.run, c.log_level) == ("bench-7", "DEBUG")
    c = cfg(["--run", "cli-run", "--log-level", "WARNING"], TAGSWARM_RUN="bench-7", TAGSWARM_LOG_LEVEL="DEBUG")
    assert (c.run, c.log_level) == ("cli-run", "WARNING")


def test_connect_comma_list() -> None:
    c = cfg(TAGSWARM_CONNECT="tcp/10.0.0.1:7447, tcp/10.0.0.2:7447,,")
    assert c.bus.connect == ("tcp/10.0.0.1:7447", "tcp/10.0.0.2:7447")
    assert c.bus.listen == ()


def test_cli_connect_replaces_env_list() -> None:
    c = cfg(["--connect", "tcp/127.0.0.1:1", "--connect", "tcp/127.0.0.1:2"],
            TAGSWARM_CONNECT="tcp/10.0.0.1:7447,tcp/10.0.0.2:7447")
    assert c.bus.connect == ("tcp/127.0.0.1:1", "tcp/127.0.0.1:2")


def test_listen_mode_and_scouting() -> None:
    c = cfg(TAGSWARM_LISTEN="tcp/0.0.0.0:7447", TAGSWARM_ZENOH_MODE="client", TAGSWARM_MULTICAST_SCOUTING="1")
    assert c.bus.listen == ("tcp/0.0.0.0:7447",)
    assert c.bus.mode == "client"
    assert c.bus.multicast_scouting is True
    c = cfg(["--zenoh-mode", "router", "--listen", "tcp/127.0.0.1:9"], TAGSWARM_ZENOH_MODE="client",
            TAGSWARM_LISTEN="tcp/0.0.0.0:7447")
    assert c.bus.mode == "router"
    assert c.bus.listen == ("tcp/127.0.0.1:9",)
    assert cfg(["--multicast-scouting"]).bus.multicast_scouting is True
    assert cfg(TAGSWARM_MULTICAST_SCOUTING="0").bus.multicast_scouting is False


def test_zenoh_lease_default_env_and_cli() -> None:
    # the default detects a frozen process within 2 s (Zenoh's own default is 10 s); see protocol/busconfig.py
    assert cfg().bus.lease_ms == DEFAULT_LEASE_MS
    assert 1000 <= DEFAULT_LEASE_MS <= 1800
    assert cfg(TAGSWARM_ZENOH_LEASE_MS="4000").bus.lease_ms == 4000
    assert cfg(["--zenoh-lease-ms", "2500"], TAGSWARM_ZENOH_LEASE_MS="4000").bus.lease_ms == 2500
    assert cfg(["--zenoh-lease-ms", " 900 "]).bus.lease_ms == 900


def test_zenoh_lease_reaches_the_zenoh_config(tmp_path: Path) -> None:
    conf = zenoh_config(cfg(["--zenoh-lease-ms", "1234"]).bus)
    assert conf.get_json("transport/link/tx/lease") == "1234"
    assert conf.get_json("transport/link/tx/keep_alive") == "4"
    # on top of a config file, like the other bus fields
    path = tmp_path / "zenoh.json5"
    path.write_text('{transport: {link: {tx: {lease: 10000}}}}')
    conf = zenoh_config(cfg(["--zenoh-config", str(path)]).bus)
    assert conf.get_json("transport/link/tx/lease") == str(DEFAULT_LEASE_MS)


def test_zenoh_config_file(tmp_path: Path) -> None:
    path = tmp_path / "zenoh.json5"
    path.write_text("{}")
    assert cfg(["--zenoh-config", str(path)]).bus.config_file == str(path)


def test_world_flags() -> None:
    c = cfg(["--render-workers", "2", "--no-spawn-workers", "--status-period", "0.5"])
    assert c.scenario.render.workers == 2
    assert c.spawn_render_workers is False
    assert c.status_period_s == 0.5
    # --render-workers is applied after --set render.workers and TAGSWARM_SET
    c = cfg(["--set", "render.workers=1", "--render-workers", "3"], TAGSWARM_SET="render.workers=4")
    assert c.scenario.render.workers == 3


def test_build_config_does_not_mutate_environ() -> None:
    environ = {"TAGSWARM_SEED": "5", "TAGSWARM_SET": "robots.count=2"}
    before = dict(environ)
    build_config(["--seed", "6"], environ)
    assert environ == before


# --------------------------------------------------------------------------- bad values


@pytest.mark.parametrize(
    ("argv", "environ", "needle"),
    [
        ([], {"TAGSWARM_SEED": "abc"}, "seed"),
        ([], {"TAGSWARM_SEED": "-1"}, "seed"),
        ([], {"TAGSWARM_ROBOTS": "0"}, "robots.count"),
        ([], {"TAGSWARM_CLOCK": "sometimes"}, "clock.mode"),
        ([], {"TAGSWARM_DURATION": "-3"}, "duration_s"),
        ([], {"TAGSWARM_SET": "nonsense"}, "nonsense"),
        ([], {"TAGSWARM_SET": "clock.tick_hz=-1"}, "clock.tick_hz"),
        ([], {"TAGSWARM_SET": "clock.bogus=1"}, "bogus"),
        ([], {"TAGSWARM_SCENARIO": "nope"}, "nope"),
        ([], {"TAGSWARM_ZENOH_MODE": "bogus"}, "mode"),
        (["--set", "robots.count=abc"], {}, "robots.count"),
        (["--set", "tags.id_stride=3"], {}, "used twice"),
        (["--set", "robot.cameras=[{width=-5}]"], {}, "robot.cameras[0].width"),
        (["--set", 'clock.mode="a\\nb"'], {}, "clock.mode"),
        (["--scenario", "nope"], {}, "nope"),
        (["--render-workers", "-1"], {}, "--render-workers"),
        (["--status-period", "0"], {}, "--status-period"),
        (["--zenoh-config", "/nonexistent/zenoh.json5"], {}, "--zenoh-config"),
        (["--zenoh-lease-ms", "fast"], {}, "--zenoh-lease-ms"),
        (["--zenoh-lease-ms", "1.5"], {}, "--zenoh-lease-ms"),
        (["--zenoh-lease-ms", "99"], {}, "--zenoh-lease-ms"),
        (["--zenoh-lease-ms", "600001"], {}, "--zenoh-lease-ms"),
        ([], {"TAGSWARM_ZENOH_LEASE_MS": "0"}, "--zenoh-lease-ms"),
        ([], {"TAGSWARM_ZENOH_LEASE_MS": ""}, "--zenoh-lease-ms"),
        (["--listen", "foo:bar"], {}, "--listen 'foo:bar': a Zenoh endpoint is PROTOCOL/ADDRESS"),
        (["--connect", "127.0.0.1:7447"], {}, "--connect '127.0.0.1:7447'"),
        ([], {"TAGSWARM_CONNECT": "tcp/10.0.0.1:7447,10.0.0.2"}, "--connect '10.0.0.2'"),
    ],
)
def test_bad_values_raise_one_line_errors(argv: list[str], environ: dict[str, str], needle: str) -> None:
    with pytest.raises(CONFIG_ERRORS) as exc:
        build_config(argv, environ)
    text = str(exc.value)
    assert "\n" not in text
    assert needle in text


def test_cli_fixes_a_bad_env_value() -> None:
    # the broken env value is overridden later, so the layered result is valid
    assert cfg(["--seed", "4"], TAGSWARM_SEED="-1").scenario.seed == 4


@pytest.mark.parametrize(("argv", "environ"), [(["--run", "a/b"], {}), ([], {"TAGSWARM_RUN": "has space"})])
def test_bad_run_id(argv: list[str], environ: dict[str, str]) -> None:
    with pytest.raises(KeyNameError) as exc:
        build_config(argv, environ)
    assert "run id" in str(exc.value)
    assert "\n" not in str(exc.value)


# --------------------------------------------------------------------------- the console entry point


def _run_world(argv: list[str], capsys: pytest.CaptureFixture[str],
               environ: dict[str, str] | None = None) -> tuple[object, str]:
    capsys.readouterr()
    try:
        code: object = node.main(argv, environ={} if environ is None else environ)
    except SystemExit as exc:
        code = exc.code
    return code, capsys.readouterr().err


@pytest.mark.parametrize(
    ("argv", "needle"),
    [
        (["--set", "tags.id_stride=3"], "tag ID 4 is used twice"),
        (["--set", "robot.cameras=[{width=-5}]"], "robot.cameras[0].width"),
        (["--scenario", "nope"], "unknown scenario 'nope'"),
        (["--bogus-flag"], "--bogus-flag"),
        (["--seed", "x"], "--seed"),
        (["--clock", "warp"], "--clock"),
        (["--run", "a/b"], "run id"),
        (["--render-workers", "-2"], "--render-workers"),
        (["--zenoh-lease-ms", "-5"], "--zenoh-lease-ms"),
    ],
)
def test_world_main_exits_2_with_one_line(argv: list[str], needle: str, capsys: pytest.CaptureFixture[str]) -> None:
    code, err = _run_world(argv, capsys)
    assert code == 2
    assert err.count("\n") == 1 and err.endswith("\n")
    assert "error" in err
    assert err.startswith("tagswarm-world: error: ")
    assert needle in err


def test_world_main_bad_env(capsys: pytest.CaptureFixture[str]) -> None:
    code, err = _run_world([], capsys, environ={"TAGSWARM_SET": "robots.count=0"})
    assert code == 2
    assert err.count("\n") == 1
    assert "robots.count" in err and "error" in err


def test_up_forwards_the_lease_and_fault_flags_to_its_children() -> None:
    from tagswarm.runtime.config import bus_from
    from tagswarm.runtime.process import child_env
    from tagswarm.up import net_flags, parser

    args = parser().parse_args(["--zenoh-lease-ms", "2500", "--net-loss", "0.1", "--net-fault-keys", "a/**"])
    want = ["--net-loss", "0.1", "--zenoh-lease-ms", "2500", "--net-fault-keys", "a/**"]
    assert net_flags(bus_from(args, {})) == want
    assert net_flags(bus_from(parser().parse_args([]), {})) == []
    # the environment is resolved by up (a flag beats it) and reaches the children as flags, never as variables
    env = {"TAGSWARM_NET_LOSS": "0.3", "TAGSWARM_NET_DELAY_MS": "20", "TAGSWARM_DURATION": "4", "PATH": "/bin",
           "TAGSWARM_SET": "agent.max_speed_m_s=0.05", "TAGSWARM_VIEW_HOST": "0.0.0.0"}
    args = parser().parse_args(["--net-loss", "0.1"])
    assert net_flags(bus_from(args, env), "DEBUG") == ["--net-loss", "0.1", "--net-delay-ms", "20.0",
                                                       "--log-level", "DEBUG"]
    assert child_env(env, keep=("TAGSWARM_VIEW_HOST",)) == {"PATH": "/bin", "TAGSWARM_VIEW_HOST": "0.0.0.0",
                                                            "PYTHONUNBUFFERED": "1"}


@pytest.mark.parametrize(("module", "positional", "refused", "kept"), [
    ("tagswarm.operator.goto", ["1", "0", "0"], ["--duration", "--robots", "--seed", "--clock", "--scenario",
                                                "--set", "--net-loss"], ["--run", "--connect"]),
    ("tagswarm.operator.kidnap", ["1", "0", "0"], ["--duration", "--robots", "--seed", "--clock", "--net-loss"],
     ["--scenario", "--set", "--run"]),
    ("tagswarm.spy.spy", [], ["--duration", "--robots", "--scenario", "--set"], ["--run", "--net-loss"]),
    ("tagswarm.deploy.alive", ["world/0"], ["--duration", "--robots", "--scenario", "--net-loss"], ["--run"]),
])
def test_tools_that_run_nothing_refuse_the_flags_that_would_do_nothing(
        module: str, positional: list[str], refused: list[str], kept: list[str],
        capsys: pytest.CaptureFixture[str]) -> None:
    import importlib

    mod = importlib.import_module(module)
    values = {"--clock": "lockstep", "--set": "seed=1", "--scenario": "paper", "--run": "r1",
              "--connect": "tcp/127.0.0.1:7447"}
    for flag in refused:
        with pytest.raises(SystemExit) as exc:
            mod.parser().parse_args([*positional, flag, values.get(flag, "1")])
        assert exc.value.code == 2
        assert f"unrecognized arguments: {flag}" in capsys.readouterr().err
    for flag in kept:
        mod.parser().parse_args([*positional, flag, values.get(flag, "1")])

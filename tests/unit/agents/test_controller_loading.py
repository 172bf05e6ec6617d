"""``--agent-module``: loading and validating a user's module (dotted name or .py file), the
agent's flag and environment variable, the one-line exit 2, and ``tagswarm up``'s
``MODULE[:ROBOTS]`` choice of robots."""

from __future__ import annotations

import sys
from collections.abc import Iterator
from pathlib import Path

import pytest

from tagswarm.agents.config import build_config
from tagswarm.agents.controller import ControlInput, Controller, ControllerConfig, Twist, load_factory, make
from tagswarm.agents.node import main as agent_main
from tagswarm.protocol.errors import UsageError
from tagswarm.protocol.scenario import load_scenario
from tagswarm.up import agent_modules

EXAMPLES = Path(__file__).resolve().parents[3] / "examples"
GOOD = "from tagswarm.agents.controller import Controller, Twist\n" \
       "class Spin(Controller):\n    def step(self, inputs):\n        return Twist(0.0, 1.0)\n" \
       "def make_controller(config):\n    return Spin()\n"


@pytest.fixture
def pkg(tmp_path: Path) -> Iterator[Path]:
    """A folder on sys.path holding user modules (removed again, with what was imported from it)."""
    sys.path.insert(0, str(tmp_path))
    before = set(sys.modules)
    try:
        yield tmp_path
    finally:
        sys.path.remove(str(tmp_path))
        for name in set(sys.modules) - before:
            if name.startswith("ctrl_"):
                del sys.modules[name]


def test_a_dotted_module_and_a_file_path_both_load(pkg: Path) -> None:
    (pkg / "ctrl_good.py").write_text(GOOD)
    for spec in ("ctrl_good", str(pkg / "ctrl_good.py")):
        ctrl = make(load_factory(spec), ControllerConfig(1, load_scenario("paper")), spec)
        assert type(ctrl).__name__ == "Spin" and isinstance(ctrl, Controller)


def test_the_example_is_importable_with_examples_on_the_path(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.syspath_prepend(str(EXAMPLES))
    factory = load_factory("controllers.circle")
    assert factory.__module__ == "controllers.circle"


@pytest.mark.parametrize(("source", "message"), [
    (None, "cannot import it: ModuleNotFoundError"),
    ("def broken(:\n", "cannot import it: SyntaxError"),
    ("raise RuntimeError('no robots here')\n", "cannot import it: RuntimeError: no robots here"),
    ("x = 1\n", "defines no make_controller(config) -> Controller"),
    ("make_controller = 3\n", "make_controller is not callable"),
])
def test_a_module_without_the_contract_is_a_one_line_error_naming_it(pkg: Path, source: str | None,
                                                                       message: str) -> None:
    name = f"ctrl_bad{abs(hash(message)) % 10_000}"
    if source is not None:
        (pkg / f"{name}.py").write_text(source)
    with pytest.raises(UsageError) as err:
        load_factory(name)
    text = str(err.value)
    assert "\n" not in text and text.startswith(f"--agent-module {name}: ") and message in text


def test_a_missing_file_and_a_factory_returning_no_controller_are_errors(pkg: Path) -> None:
    with pytest.raises(UsageError, match="no such file"):
        load_factory(str(pkg / "nope.py"))
    (pkg / "ctrl_wrong.py").write_text("def make_controller(config):\n    return object()\n")
    factory = load_factory("ctrl_wrong")
    with pytest.raises(UsageError, match=r"returned object, not a tagswarm\.agents\.controller\.Controller"):
        make(factory, ControllerConfig(1, load_scenario("paper")), "ctrl_wrong")
    (pkg / "ctrl_raises.py").write_text("def make_controller(config):\n    raise KeyError('gain')\n")
    with pytest.raises(UsageError, match="make_controller raised KeyError"):
        make(load_factory("ctrl_raises"), ControllerConfig(1, load_scenario("paper")), "ctrl_raises")


def test_the_agent_takes_the_flag_over_the_environment(pkg: Path) -> None:
    (pkg / "ctrl_a.py").write_text(GOOD)
    (pkg / "ctrl_b.py").write_text(GOOD)
    assert build_config(["--robot-id", "1"], {}).agent_module is None
    assert build_config(["--robot-id", "1"], {"TAGSWARM_AGENT_MODULE": "ctrl_a"}).agent_module == "ctrl_a"
    both = build_config(["--robot-id", "1", "--agent-module", "ctrl_b"], {"TAGSWARM_AGENT_MODULE": "ctrl_a"})
    assert both.agent_module == "ctrl_b"
    with pytest.raises(UsageError, match="ctrl_missing"):
        build_config(["--robot-id", "1"], {"TAGSWARM_AGENT_MODULE": "ctrl_missing"})


def test_the_agent_exits_2_with_one_line_naming_the_module(capsys: pytest.CaptureFixture[str]) -> None:
    code = agent_main(["--robot-id", "1", "--agent-module", "ctrl_not_there.sub"], {})
    err = capsys.readouterr().err.strip()
    assert code == 2 and "\n" not in err
    assert err.startswith("tagswarm-agent: error: --agent-module ctrl_not_there.sub: cannot import it")


def test_up_chooses_robots_per_module(pkg: Path) -> None:
    (pkg / "ctrl_x.py").write_text(GOOD)
    (pkg / "ctrl_y.py").write_text(GOOD)
    ids = (0, 1, 2, 3)
    assert agent_modules([], ids) == {}
    assert agent_modules(["ctrl_x"], ids) == dict.fromkeys(ids, "ctrl_x")
    assert agent_modules(["ctrl_x:1,3", "ctrl_y:2"], ids) == {1: "ctrl_x", 3: "ctrl_x", 2: "ctrl_y"}
    path = str(pkg / "ctrl_x.py")
    assert agent_modules([f"{path}:0"], ids) == {0: path}
    for specs, message in ((["ctrl_x:7"], "robot 7 is not in this run"),
                           (["ctrl_x:1", "ctrl_y:1,2"], "robot 1 already has controller ctrl_x"),
                           (["ctrl_x:1,,2"], "ROBOTS must be robot ids like 1,3"),
                           (["ctrl_x.py:a"], "ROBOTS must be robot ids like 1,3"),
                           ([":1"], "no module named"),
                           (["ctrl_zz:1"], "--agent-module ctrl_zz: cannot import it")):
        with pytest.raises(UsageError, match=message):
            agent_modules(specs, ids)


def test_up_calls_make_controller_for_each_robot_before_anything_starts(pkg: Path) -> None:
    """A factory that raises or returns no Controller is the same one-line error in ``tagswarm up`` as in
    the agent (before: the run started, the agents exited 2, and the report was full of nan)."""
    s = load_scenario("paper", ["robots.count=3"])
    (pkg / "ctrl_ok.py").write_text(GOOD)
    (pkg / "ctrl_raises.py").write_text("def make_controller(config):\n    raise RuntimeError('no weights file')\n")
    (pkg / "ctrl_none.py").write_text("def make_controller(config):\n    return None\n")
    (pkg / "ctrl_only2.py").write_text(GOOD.replace("    return Spin()", "    assert config.robot_id != 2, 'not 2'\n"
                                                    "    return Spin()"))
    assert agent_modules(["ctrl_ok"], s.robot_ids, s) == dict.fromkeys(s.robot_ids, "ctrl_ok")
    assert agent_modules(["ctrl_only2:0,1"], s.robot_ids, s) == {0: "ctrl_only2", 1: "ctrl_only2"}
    for spec, message in (("ctrl_raises", "make_controller raised RuntimeError: no weights file"),
                          ("ctrl_none", "make_controller returned NoneType, not a"),
                          ("ctrl_only2", "make_controller raised AssertionError: not 2")):
        with pytest.raises(UsageError, match=f"--agent-module {spec}: {message}"):
            agent_modules([spec], s.robot_ids, s)
    assert agent_modules(["ctrl_raises"], s.robot_ids) == dict.fromkeys(s.robot_ids, "ctrl_raises")  # no scenario


def test_the_controllers_in_the_docs_load_and_drive(tmp_path: Path) -> None:
    text = (EXAMPLES.parent / "docs" / "controllers.md").read_text()
    blocks = [b.split("```", 1)[0] for b in text.split("```python\n")[1:]]
    modules = [b for b in blocks if "def make_controller" in b]
    assert len(modules) == 2
    for k, source in enumerate(modules):
        path = tmp_path / f"doc_ctrl_{k}.py"
        path.write_text(source)
        ctrl = make(load_factory(str(path)), ControllerConfig(1, load_scenario("paper")), str(path))
        cmd = ctrl.step(ControlInput(robot_id=1, t_s=0.0, localised=True, pose=(1.0, 0.0, 0.0), pose_cov=(0.0,) * 9,
                                     odom=(0.0, 0.0, 0.0), odom_cov=(0.0,) * 9, distance_m=0.0, moved=False,
                                     fix=True, server_up=True))
        assert isinstance(cmd, Twist) and (cmd.v_m_s, cmd.w_rad_s) != (0.0, 0.0)

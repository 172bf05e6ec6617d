"""tagswarm.view.view: configuration, the page's select messages and the hub (no network)."""

from __future__ import annotations

import json

import pytest

from tagswarm.protocol.keys import KeyNameError
from tagswarm.runtime.config import ConfigError
from tagswarm.view import view, webserver


def test_defaults_and_precedence() -> None:
    cfg = view.build_config([], environ={})
    assert (cfg.host, cfg.port, cfg.run, cfg.rate_hz) == ("127.0.0.1", view.DEFAULT_PORT, "default", 10.0)
    assert cfg.scenario.name == "paper" and cfg.bus.connect == ()
    env = {"TAGSWARM_VIEW_PORT": "9001", "TAGSWARM_RUN": "fromenv", "TAGSWARM_CONNECT": "tcp/127.0.0.1:7447"}
    cfg = view.build_config([], environ=env)
    assert (cfg.port, cfg.run, cfg.bus.connect) == (9001, "fromenv", ("tcp/127.0.0.1:7447",))
    cfg = view.build_config(["--port", "0", "--run", "flag", "--robots", "2", "--host", "0.0.0.0"], environ=env)
    assert (cfg.port, cfg.run, cfg.host, cfg.scenario.robots.count) == (0, "flag", "0.0.0.0", 2)


@pytest.mark.parametrize(("argv", "env", "error"), [
    (["--port", "70000"], {}, ConfigError),
    ([], {"TAGSWARM_VIEW_PORT": "http"}, ConfigError),
    (["--rate", "0"], {}, ConfigError),
    (["--camera-rate", "100"], {}, ConfigError),
    (["--thumb-width", "8"], {}, ConfigError),
    (["--run", "a/b"], {}, KeyNameError),
])
def test_bad_configuration_is_one_clear_error(argv: list[str], env: dict[str, str], error: type) -> None:
    with pytest.raises(error):
        view.build_config(argv, environ=env)


def test_bad_flags_exit_2(capsys: pytest.CaptureFixture[str]) -> None:
    assert view.main(["--port", "-1"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("tagswarm view: error: --port") and "\n" not in err


@pytest.mark.parametrize(("text", "expect"), [
    ('{"type": "select", "robot": 3}', 3),
    ('{"type": "select", "robot": null}', None),
    ('{"type": "select", "robot": -1}', False),
    ('{"type": "select", "robot": true}', False),
    ('{"type": "select", "robot": "3"}', False),
    ('{"type": "hello"}', False),
    ("[1, 2]", False),
    ("not json", False),
    (b"\xff\xfe", False),
])
def test_select_messages_from_the_page(text: str | bytes, expect: object) -> None:
    assert repr(webserver._select_message(text)) == repr(expect)  # False (ignored) must not pass for robot 0


def test_hub_tracks_selections_and_versions() -> None:
    hub = webserver.Hub(json.dumps({"type": "scene"}))
    a, b = hub.join(), hub.join()
    hub.select(a, 2)
    hub.select(b, None)
    assert hub.wanted_cameras() == {2}
    hub.leave(a)
    assert hub.wanted_cameras() == set()
    v0 = hub.state()[0]
    hub.publish_state('{"type":"state"}')
    assert hub.state() == (v0 + 1, '{"type":"state"}')
    assert hub.camera(1) is None
    hub.publish_camera(1, "x")
    hub.publish_camera(1, "y")
    assert hub.camera(1) == (2, "y") and hub.camera(None) is None

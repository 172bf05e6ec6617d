"""The world's start-up log says what each lens costs to render (a user's first clue to a slow
wide-lens scene); no network (the in-memory bus of test_world_command)."""

from __future__ import annotations

import logging

import pytest

from tagswarm.protocol.scenario import load_scenario
from tests.unit.world.test_world_command import BASE, make_node


def test_a_fisheye_is_logged_with_its_renders_and_a_pinhole_is_not(caplog: pytest.LogCaptureFixture) -> None:
    fish = 'robot.cameras=[{name="wide", width=320, height=240, hfov_deg=120, rate_hz=1}]'
    with caplog.at_level(logging.INFO, logger="tagswarm.world"):
        node, _, _ = make_node(load_scenario("paper", [*BASE, fish, "camera.preset=realistic"]))
        node.close()
    lines = [r.getMessage() for r in caplog.records if r.getMessage().startswith("camera wide:")]
    assert lines == ["camera wide: fisheye lens 120deg, rendered as 600x452 + a 342x342 fovea at full resolution "
                     "(5.1x its 320x240 pixels)"]
    caplog.clear()
    with caplog.at_level(logging.INFO, logger="tagswarm.world"):
        node, _, _ = make_node(load_scenario("paper", BASE))
        node.close()
    assert not [r for r in caplog.records if r.getMessage().startswith("camera ")]

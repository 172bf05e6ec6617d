"""The automatic render.workers (-1): chosen from the cores and the cameras' load."""

from __future__ import annotations

import pytest

from tagswarm.protocol.scenario import Scenario, load_scenario
from tagswarm.world.config import (
    AUTO_WORKERS,
    RENDER_S_PER_PIXEL,
    auto_render_workers,
    build_config,
    render_load,
    resolve_render_workers,
)


def hall(robots: int, *more: str) -> Scenario:
    # hall has no [render] section: the schema's default
    return load_scenario("hall", [f"robots.count={robots}", *more])


def test_the_default_is_automatic() -> None:
    assert hall(2).render.workers == AUTO_WORKERS


@pytest.mark.parametrize(("robots", "cores", "workers"), [
    (1, 2, 0), (4, 2, 0),  # light: in the world process
    (5, 2, 1), (8, 2, 2), (16, 2, 2),  # one per 0.3 core of rendering, at most one per core
    (16, 8, 3), (16, 1, 0),  # more cores: more workers; a single core: in-process
])
def test_workers_follow_the_render_load_and_the_cores(robots: int, cores: int, workers: int) -> None:
    assert auto_render_workers(hall(robots), cores) == workers


def test_load_counts_pixels_rate_and_robots() -> None:
    small = render_load(hall(8))
    assert render_load(hall(16)) == pytest.approx(2 * small)
    big = hall(8, 'robot.cameras=[{name="front", width=640, height=480, hfov_deg=60, rate_hz=5}]')
    assert render_load(big) == pytest.approx(2 * small)


def test_lockstep_renders_in_process() -> None:
    assert auto_render_workers(hall(16, 'clock.mode="lockstep"'), 8) == 0


def test_a_set_number_is_kept_and_auto_is_resolved() -> None:
    s = hall(16, "render.workers=1")
    assert resolve_render_workers(s, cores=2) is s
    assert resolve_render_workers(hall(16), cores=2).render.workers == 2
    assert resolve_render_workers(hall(2), cores=2).render.workers == 0


def test_the_world_config_holds_a_resolved_number() -> None:
    c = build_config(["--scenario", "hall", "--robots", "2"], {})
    assert c.scenario.render.workers == 0
    c = build_config(["--scenario", "hall", "--robots", "3", "--render-workers", "3"], {})
    assert c.scenario.render.workers == 3


def test_without_spawned_workers_automatic_means_in_process() -> None:
    # workers started by hand (compose) must be told their number: auto would wait for workers nobody starts
    c = build_config(["--scenario", "hall", "--robots", "16", "--clock", "realtime", "--no-spawn-workers"], {})
    assert c.scenario.render.workers == 0


def test_a_lens_counts_the_pixels_it_renders() -> None:
    """A 120 deg fisheye renders a wide pinhole and a fovea, ~5x its image's pixels: the load says so
    (it once counted the image's own pixels, a third of what a rig's world then had to render)."""
    pin = hall(8, 'robot.cameras=[{name="front", width=320, height=240, hfov_deg=60}]', "camera.preset=realistic")
    fish = hall(8, 'robot.cameras=[{name="front", width=320, height=240, hfov_deg=120}]', "camera.preset=realistic")
    ideal = hall(8, 'robot.cameras=[{name="front", width=320, height=240, hfov_deg=60}]')
    assert render_load(ideal) == pytest.approx(8 * 320 * 240 * 10 * RENDER_S_PER_PIXEL)
    assert 1.2 < render_load(pin) / render_load(ideal) < 2.0  # a Brown-Conrady lens's wider render, the model
    assert render_load(fish) / render_load(ideal) > 5.0

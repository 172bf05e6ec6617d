"""The world process's one frozen config, built from scenario, environment and flags."""

from __future__ import annotations

import argparse
import functools
import math
import os
from collections.abc import Mapping, Sequence

import msgspec

from tagswarm.protocol.bus import BusConfig
from tagswarm.protocol.scenario import Camera, Scenario
from tagswarm.runtime.config import ConfigError, Invocation, OneLineParser, add_common_args
from tagswarm.world.lens import RenderPlan, plan

AUTO_WORKERS = -1  # render.workers: let the world choose (auto_render_workers)
# TinyRenderer's cost per pixel of a camera frame on the 2-core development machine: 5.3 ms for
# 320x240 with 16 robots in the arena, of which 2.1 ms are pybullet's fixed per-pixel work
# (clearing and copying the buffers) and the rest the walls and robots (bench/render.py)
RENDER_S_PER_PIXEL = 7e-8
IN_PROCESS_MAX_CORES = 0.25  # rendering this much still leaves the world's own loop its tick
PER_WORKER_CORES = 0.3  # a worker busier than this skips requests at the bursts of staggered cameras


EFFECTS_LOAD = 1.2  # the realistic camera's model (remap, blur, noise) after its renders: ~0.2 of them


@functools.lru_cache(maxsize=64)
def lens_plan(cam: Camera, preset: str) -> RenderPlan:
    """:func:`~tagswarm.world.lens.plan` of ``cam``, made once per process (10-100 ms for a lens)."""
    return plan(cam, preset)


def render_pixels(cam: Camera, preset: str) -> int:
    """Pixels pybullet renders for one frame of ``cam``: the image's, or a lens's wider pinhole
    render and a wide lens's fovea (world/lens.py: a 320x240 120 deg fisheye renders 5.1x its pixels)."""
    p = lens_plan(cam, preset)
    fovea = 0 if p.fovea is None else p.fovea.render_cam.width * p.fovea.render_cam.height
    return p.render_cam.width * p.render_cam.height + fovea


def render_load(scenario: Scenario) -> float:
    """Cores that rendering the scenario's cameras takes at real time (an estimate: rendered pixels
    per second x :data:`RENDER_S_PER_PIXEL`, times :data:`EFFECTS_LOAD` with the realistic camera's effects)."""
    preset = scenario.camera.preset
    pixels_per_s = len(scenario.robot_ids) * sum(render_pixels(c, preset) * c.rate_hz for c in scenario.robot.cameras)
    return pixels_per_s * RENDER_S_PER_PIXEL * (EFFECTS_LOAD if scenario.camera.has_effects else 1.0)


def usable_cores() -> int:
    """CPUs this process may run on (the affinity mask, e.g. a container's share)."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # not on Linux
        return os.cpu_count() or 1


def auto_render_workers(scenario: Scenario, cores: int) -> int:
    """The automatic ``render.workers`` (-1): 0 (render in the world process) in lockstep (the
    world waits for every frame anyway, and workers would add a round trip a step), on a single
    core, or when the renders take at most :data:`IN_PROCESS_MAX_CORES`; otherwise enough workers
    for :data:`PER_WORKER_CORES` each, at most one per core.  On 2 cores at 320x240 / 10 Hz: 0 up
    to 4 robots, 1 at 5, 2 from 6 on."""
    if scenario.clock.mode == "lockstep" or cores < 2:
        return 0
    load = render_load(scenario)
    if load <= IN_PROCESS_MAX_CORES:
        return 0
    return min(cores, max(1, math.ceil(load / PER_WORKER_CORES)))


def resolve_render_workers(scenario: Scenario, cores: int | None = None) -> Scenario:
    """``scenario`` with an automatic ``render.workers`` (-1) replaced by :func:`auto_render_workers`
    (``cores``: default :func:`usable_cores`); a set number is kept."""
    if scenario.render.workers != AUTO_WORKERS:
        return scenario
    k = auto_render_workers(scenario, usable_cores() if cores is None else cores)
    return msgspec.structs.replace(scenario, render=msgspec.structs.replace(scenario.render, workers=k))


class WorldConfig(msgspec.Struct, frozen=True, kw_only=True):
    """Everything the world process needs; built once in ``main``."""

    scenario: Scenario
    bus: BusConfig
    run: str = "default"
    status_period_s: float = 1.0
    spawn_render_workers: bool = True
    log_level: str = "INFO"


def parser(prog: str = "tagswarm-world") -> argparse.ArgumentParser:
    p = OneLineParser(
        prog=prog,
        description="The tagswarm world: steps the pybullet arena, renders every robot's cameras and publishes "
        "images, encoder ticks, ground truth and the clock over Zenoh; takes wheel commands.",
    )
    add_common_args(p)
    p.add_argument("--render-workers", type=int, metavar="K",
                   help="render in K worker processes (0 = in this process; default: render.workers, whose "
                        "default -1 chooses from the cores and the cameras' load); same as --set render.workers=K")
    p.add_argument("--no-spawn-workers", action="store_true",
                   help="do not start render workers; expect them to be started separately (compose): give their "
                        "number with --render-workers (the automatic render.workers means 0 here)")
    p.add_argument("--status-period", type=float, default=1.0, metavar="SECONDS",
                   help="simulated seconds between status messages (default 1)")
    return p


def build_config(argv: Sequence[str] | None = None, environ: Mapping[str, str] | None = None) -> WorldConfig:
    """Parse flags and environment into a :class:`WorldConfig`; raises ConfigError /
    ScenarioError with a one-line message."""
    inv = Invocation(parser(), argv, environ)
    args = inv.args
    if args.render_workers is not None:
        if args.render_workers < 0:
            raise ConfigError("--render-workers must be >= 0")
        args.overrides.append(f"render.workers={args.render_workers}")
    scenario = inv.scenario()
    if args.no_spawn_workers and scenario.render.workers == AUTO_WORKERS:
        # workers started by someone else: only a number they were told is theirs to match
        scenario = msgspec.structs.replace(scenario, render=msgspec.structs.replace(scenario.render, workers=0))
    scenario = resolve_render_workers(scenario)
    run = inv.run()
    if args.status_period <= 0:
        raise ConfigError("--status-period must be > 0")
    return WorldConfig(scenario=scenario, bus=inv.bus(), run=run, status_period_s=args.status_period,
                       spawn_render_workers=not args.no_spawn_workers, log_level=inv.log_level())

"""Render workers (separate processes holding visual replicas) publish exactly
the frames the world would have rendered itself."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from tagswarm.protocol import codec
from tagswarm.protocol import messages as m
from tagswarm.protocol.keys import Keys
from tagswarm.world.node import due
from tests.harness import Participant, client, endpoint, process, script, world_argv

SCENE = ['clock.mode="lockstep"', 'clock.participants=["agent/0"]', "robots.count=4", "seed=5",
         'robot.cameras=[{name="front", rate_hz=10}, {name="rear", yaw_deg=180, rate_hz=5}]', "duration_s=30"]


def _frames(argv: list[str], ep: str, run: str, steps: int, log: Path) -> dict[tuple[int, int, str], bytes]:
    keys = Keys(run)
    expected: set[tuple[int, int, str]] = set()
    got: dict[tuple[int, int, str], bytes] = {}
    with process(argv, log), client(ep) as bus:
        images = bus.subscribe(keys.images())
        me = Participant(bus, keys, "agent/0")

        def drain() -> bool:
            for it in images.drain():
                img = codec.decode(m.CameraImage, it.value)
                got[(img.step, img.robot_id, img.camera)] = img.data
            return expected <= set(got)

        def on_tick(tick: m.Tick) -> bool:
            # a worker's first frames can go out before the peer-to-peer link from that worker to
            # this test's session is up (peers discover each other by gossip); judge from step 3 on
            for pair in (tick.cameras_rendered if tick.step >= 3 else ()):
                rid, cam = pair.split("/")
                expected.add((tick.step, int(rid), cam))
            drain()
            return tick.step < steps

        me.serve(on_tick)
        assert bus.wait_for(drain, 30), f"missing frames {sorted(expected - set(got))[:5]}"
    return {k: v for k, v in got.items() if k in expected}


def test_two_workers_render_the_same_frames_as_the_world(tmp_path: Path) -> None:
    ep1, ep2 = endpoint(), endpoint()
    local = _frames(world_argv(ep1, "local", *SCENE), ep1, "local", 12, tmp_path / "local.log")
    tagswarm = [script("tagswarm"), "world", "--listen", ep2, "--run", "workers", "--render-workers", "2"]
    for o in SCENE:
        tagswarm += ["--set", o]
    remote = _frames(tagswarm, ep2, "workers", 12, tmp_path / "workers.log")
    # steps 3..12 of a 30 Hz clock: the 8 cameras (front 10 Hz, rear 5 Hz, 4 robots); robot j's
    # cameras fire at phase j/4 of their periods: 4 or 3 front frames and 2 or 1 rear frames each
    rates = [10.0, 5.0] * 4
    assert len(local) == sum(due(k, r, 30.0, (i // 2) / 4) for i, r in enumerate(rates) for k in range(3, 13)) == 21
    assert set(remote) == set(local)
    for key, data in local.items():
        assert remote[key] == data, f"frame {key} differs"
    # frames are real renders, not blank: other robots and walls show up
    assert all(np.frombuffer(d, np.uint8).std() > 5 for d in local.values())
    log = (tmp_path / "workers.log").read_text()
    assert "render/0 joined" in log and "render/1 joined" in log

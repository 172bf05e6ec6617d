"""A render worker process: a visual-only replica of the scene that renders a
subset of the robots' cameras and publishes them under the robots' image keys.

The world sends :class:`~tagswarm.protocol.messages.RenderPoses` (all robot poses plus
the cameras this worker must render) on ``world/render/<i>``; the worker renders,
publishes each :class:`~tagswarm.protocol.messages.CameraImage`, then acknowledges the
step as participant ``render/<i>``.  In realtime mode the request inbox is
newest-only, so a slow worker skips frames instead of queueing them.  Its
counters (frames, rejected requests per kind) go out as an
:class:`~tagswarm.protocol.messages.AgentStatus` with role ``render/<i>`` on the world's
status key, every simulated second and when it stops.
"""

from __future__ import annotations

import argparse
import logging
import threading
from collections import Counter
from collections.abc import Mapping, Sequence

import msgspec

from tagswarm.protocol import codec
from tagswarm.protocol import messages as m
from tagswarm.protocol.bus import Bus, BusConfig
from tagswarm.protocol.keys import Keys
from tagswarm.protocol.scenario import Scenario
from tagswarm.runtime import streams
from tagswarm.runtime.config import ConfigError, Invocation, OneLineParser, add_common_args
from tagswarm.runtime.lockstep import Participant
from tagswarm.runtime.process import serve_node
from tagswarm.world.render import Renderer, image_message, pose_matrix

log = logging.getLogger("tagswarm.render")
STATUS_PERIOD_NS = 1_000_000_000


class RenderConfig(msgspec.Struct, frozen=True, kw_only=True):
    scenario: Scenario
    bus: BusConfig
    worker_index: int
    run: str = "default"
    log_level: str = "INFO"


def build_config(argv: Sequence[str] | None = None, environ: Mapping[str, str] | None = None) -> RenderConfig:
    p: argparse.ArgumentParser = OneLineParser(
        prog="tagswarm-render",
        description="A tagswarm render worker: renders a share of the robots' cameras for the world process.")
    add_common_args(p)
    p.add_argument("--worker-index", type=int, required=True, metavar="I", help="this worker's index, 0..K-1")
    inv = Invocation(p, argv, environ)
    args = inv.args
    scenario = inv.scenario()
    if not 0 <= args.worker_index < max(scenario.render.workers, 1):
        raise ConfigError(f"--worker-index {args.worker_index} is outside 0..{scenario.render.workers - 1} "
                          "(render.workers)")
    run = inv.run()
    return RenderConfig(scenario=scenario, bus=inv.bus(), worker_index=args.worker_index, run=run,
                        log_level=inv.log_level())


class RenderWorkerNode:
    """Renders the cameras the world assigns to this worker."""

    def __init__(self, config: RenderConfig, bus: Bus) -> None:
        self.cfg = config
        self.s = config.scenario
        self.bus = bus
        self.keys = Keys(config.run)
        self.name = f"render/{config.worker_index}"
        self.renderer = Renderer(self.s)
        self.cams = {c.name: c for c in self.s.robot.cameras}
        self.rejects = streams.RejectCounter(log)
        self.counters: Counter[str] = Counter()
        self.seq = streams.Sequencer()
        self.participant = Participant(bus, self.keys, self.name, self.seq)  # acks every request, lockstep or not
        self.time_ns = 0
        self._next_status_ns = 0
        lockstep = self.s.clock.mode == "lockstep"
        self.req_in = bus.subscribe(self.keys.render(config.worker_index), newest_only=not lockstep)
        bus.declare_token(self.keys.alive(self.name))

    def step(self) -> int:
        """Render every pending request; returns the number of frames published."""
        before = self.counters["frames_rendered"]
        requests = (req for _, req in self.rejects.decoded(self.req_in.drain(), m.RenderPoses))
        self.participant.serve(requests, self._render, acked=self._after_step)
        return self.counters["frames_rendered"] - before

    def _after_step(self, req: m.RenderPoses) -> None:
        """The status, at most every STATUS_PERIOD_NS of simulation time (after the ack: the
        world need not wait for it)."""
        self.time_ns = max(self.time_ns, req.stamp_ns)
        if self.time_ns >= self._next_status_ns:
            self.publish_status()
            self._next_status_ns = self.time_ns + STATUS_PERIOD_NS

    def publish_status(self) -> None:
        """Counters and rejects, on the world's status key (the worker is part of the world)."""
        key = self.keys.world_status()
        counters = {**self.counters, **self.rejects.as_counters()}
        self.bus.put(key, codec.encode(m.AgentStatus(seq=self.seq.next(key), stamp_ns=self.time_ns, role=self.name,
                                                     mode=self.s.clock.mode, counters=counters)))

    def _render(self, req: m.RenderPoses) -> bool:
        """Render and publish the cameras ``req`` asks for (counted in ``frames_rendered``); a
        request is always answered, so the world is never held up by a bad camera name."""
        bases = {}
        for rid, p in zip(req.robot_ids, req.poses, strict=False):
            if rid in self.renderer.bodies:
                pos, quat = (p.x_m, p.y_m, p.z_m), (p.qx, p.qy, p.qz, p.qw)
                self.renderer.set_pose(rid, pos, quat)
                bases[rid] = pose_matrix(pos, quat)
        n = 0
        for pair in req.cameras:
            rid_s, _, cam_name = pair.partition("/")
            cam = self.cams.get(cam_name)
            if not rid_s.isdigit() or int(rid_s) not in bases or cam is None:
                self.rejects.reject("unknown_camera", f"render request for {pair!r}")
                continue
            rid = int(rid_s)
            img = self.renderer.render(rid, cam, bases[rid])
            key = self.keys.image(rid, cam.name)
            self.bus.put(key, codec.encode(image_message(self.s, rid, cam, img, seq=self.seq.next(key), step=req.step,
                                                         stamp_ns=req.stamp_ns)),
                         drop=self.s.clock.mode != "lockstep")  # lockstep: BLOCK (see world/node.py)
            n += 1
        self.counters["frames_rendered"] += n
        return True

    def run(self, stop_event: threading.Event) -> int:
        while not stop_event.is_set():
            if not self.step():
                self.bus.wait(0.2)
        self.publish_status()
        return 0

    def close(self) -> None:
        self.renderer.close()


def main(argv: Sequence[str] | None = None, environ: Mapping[str, str] | None = None) -> int:
    """Console script ``tagswarm-render``."""

    return serve_node("tagswarm-render", lambda: build_config(argv, environ), lambda c: f"render{c.worker_index}",
                      RenderWorkerNode)


if __name__ == "__main__":
    raise SystemExit(main())

"""``tagswarm view``: a live web view of a running system (``tagswarm up``, compose or a replay).

Joins the Zenoh network like any tool (``--connect``, ``--run``, ``--scenario`` ...)
as a read-only subscriber (no liveliness token: it never joins a lockstep) and
serves one page on ``http://127.0.0.1:8765/`` (``--host``, ``--port``) that
draws the arena live in SVG: walls and obstacles from the scenario, every
robot's true pose, fused pose with its 95 % covariance ellipse, odometry-only
pose, who sees whom, each agent's mode and share of time localised, the
server's re-localisation events and kidnaps (a marker at the robot for a few
seconds, and a list), the simulation time and real-time factor, and the
camera of a selected robot with the agent's detections reprojected onto it.
Plain HTML/JS/CSS shipped in ``tagswarm/web``: no build step, nothing fetched
from the internet.

Threads: Zenoh callbacks only enqueue (:mod:`tagswarm.protocol.bus`); the node's loop
(:meth:`ViewNode.step`) drains, decodes (bad payloads are counted per kind and
dropped), folds messages into :class:`~tagswarm.view.state.ViewState` and hands a
JSON snapshot to the :class:`Hub` at most ``--rate`` times a second (default
10); one server thread per browser sends each new snapshot (never more often
than that) and the selected robot's camera (at most ``--camera-rate``).

Page protocol (JSON text frames on ``/ws``): server to page ``scene`` (static
arena, once per connection), ``state`` (see :meth:`ViewState.snapshot`) and
``camera`` (see :func:`tagswarm.view.thumbnails.camera_message`); page to server
``{"type": "select", "robot": K}`` chooses the camera shown.  ``GET
/state.json`` returns the newest snapshot (for scripts).
"""

from __future__ import annotations

import argparse
import json
import logging
import threading
import time
from collections import deque
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Final

from tagswarm.protocol import codec
from tagswarm.protocol import messages as m
from tagswarm.protocol.bus import Bus, BusConfig, Inbox
from tagswarm.protocol.keys import Keys
from tagswarm.protocol.scenario import Scenario
from tagswarm.runtime import streams
from tagswarm.runtime.config import ConfigError, Invocation, OneLineParser, add_common_args
from tagswarm.runtime.process import serve_node
from tagswarm.view.state import ViewState
from tagswarm.view.thumbnails import camera_message
from tagswarm.view.webserver import Hub, WebServer

PROG = "tagswarm view"
log = logging.getLogger("tagswarm.view")

DEFAULT_PORT: Final = 8765
#: Frames kept per robot: the overlay uses one that is old enough for the agent to have
#: published its observations of it (they arrive a few ms after the frame).
FRAMES_KEPT: Final = 3
FRAME_SETTLE_S: Final = 0.15
#: Observations kept per observer to match a frame's stamp.
OBSERVATIONS_KEPT: Final = 64


# --------------------------------------------------------------------------- config


@dataclass(frozen=True)
class ViewConfig:
    """Everything ``tagswarm view`` needs, resolved once (TOML < TAGSWARM_* < flags)."""

    scenario: Scenario
    run: str
    bus: BusConfig
    host: str = "127.0.0.1"
    port: int = DEFAULT_PORT
    rate_hz: float = 10.0
    camera_rate_hz: float = 5.0
    thumb_width: int = 320
    log_level: str = "INFO"


def parser() -> OneLineParser:
    p = OneLineParser(prog=PROG, description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_common_args(p)
    w = p.add_argument_group("web server")
    w.add_argument("--host", help="address to serve on (env TAGSWARM_VIEW_HOST; default 127.0.0.1: this "
                                  "machine only)")
    w.add_argument("--port", type=int, help=f"HTTP port, 0 = any free one (env TAGSWARM_VIEW_PORT; "
                                            f"default {DEFAULT_PORT})")
    w.add_argument("--rate", type=float, default=10.0, metavar="HZ", help="page updates per second (default 10)")
    w.add_argument("--camera-rate", type=float, default=5.0, metavar="HZ",
                   help="camera thumbnails per second (default 5)")
    w.add_argument("--thumb-width", type=int, default=320, metavar="PX",
                   help="camera thumbnails are downscaled to this width (default 320)")
    return p


def build_config(argv: Sequence[str] | None, environ: Mapping[str, str] | None = None) -> ViewConfig:
    """Parse flags and environment into a :class:`ViewConfig`; raises :class:`ConfigError`."""
    inv = Invocation(parser(), argv, environ)
    args, env = inv.args, inv.env
    port_raw = args.port if args.port is not None else env.get("TAGSWARM_VIEW_PORT", DEFAULT_PORT)
    try:
        port = int(port_raw)
    except ValueError:
        raise ConfigError(f"TAGSWARM_VIEW_PORT: not a port number: {port_raw!r}") from None
    if not 0 <= port <= 65535:
        raise ConfigError(f"--port must be 0..65535, got {port}")
    if not 0 < args.rate <= 60:
        raise ConfigError(f"--rate must be in (0, 60] Hz, got {args.rate:g}")
    if not 0 < args.camera_rate <= 30:
        raise ConfigError(f"--camera-rate must be in (0, 30] Hz, got {args.camera_rate:g}")
    if not 32 <= args.thumb_width <= 4096:
        raise ConfigError(f"--thumb-width must be 32..4096 px, got {args.thumb_width}")
    run = inv.run()
    return ViewConfig(scenario=inv.scenario(), run=run, bus=inv.bus(),
                      host=args.host or env.get("TAGSWARM_VIEW_HOST", "127.0.0.1"), port=port,
                      rate_hz=args.rate, camera_rate_hz=args.camera_rate, thumb_width=args.thumb_width,
                      log_level=inv.log_level())


# --------------------------------------------------------------------------- node


class ViewNode:
    """Subscribes read-only to a run and feeds the web page; see the module docstring."""

    def __init__(self, config: ViewConfig, bus: Bus) -> None:
        self.cfg = config
        self.bus = bus
        self.keys = k = Keys(config.run)
        self.rejects = streams.RejectCounter(log)
        self.state = ViewState(config.scenario, k, self.rejects)
        self.hub = Hub(json.dumps(self.state.scene()))
        # (inbox, message type): the tick is newest-only (only the latest clock matters)
        self.inboxes: list[tuple[Inbox[bytes], type[m.Msg]]] = [
            (bus.subscribe(k.tick(), newest_only=True), m.Tick),
            (bus.subscribe(k.map()), m.GlobalMap),
            (bus.subscribe(k.truth()), m.GroundTruthPose),
            (bus.subscribe(k.correction()), m.Correction),
            (bus.subscribe(k.odometry()), m.OdometryEstimate),
            (bus.subscribe(k.robot_status()), m.AgentStatus),
            (bus.subscribe(k.server_status()), m.AgentStatus),
            (bus.subscribe(k.world_status()), m.AgentStatus),
            (bus.subscribe(k.relocalisation()), m.Relocalisation),
            (bus.subscribe(k.world_command()), m.WorldCommand),
        ]
        self.obs_in = bus.subscribe(k.observation())
        self.cam_in = bus.subscribe(k.images(), capacity=64)
        self.frames: dict[int, deque[tuple[float, str, bytes]]] = {}
        self.observations: dict[int, deque[m.RelativeObservation]] = {}
        self._next_state_s = 0.0
        self._next_cam_s = 0.0
        self._published_version = -1
        self._cam_sent: dict[int, int] = {}
        self.server = WebServer(config.host, config.port, self.hub)

    @property
    def url(self) -> str:
        return self.server.url

    def _key_robot(self, key: str, rid: int) -> bool:
        if self.keys.robot_id_of(key) == rid:
            return True
        self.rejects.reject("mismatched_key", f"{key} carries robot {rid}")
        return False

    def step(self, now_s: float | None = None) -> bool:
        """Drain, decode and fold everything that arrived; publish a snapshot when due.
        Returns whether anything arrived."""
        now = time.monotonic() if now_s is None else now_s
        got = False
        for inbox, cls in self.inboxes:
            items = inbox.drain()
            got = got or bool(items)
            for item, msg in self.rejects.decoded(items, cls):
                self.state.apply(msg, item.key if cls is not m.GlobalMap else None, now)
        obs_items = self.obs_in.drain()
        for item, ob in self.rejects.decoded(obs_items, m.RelativeObservation):
            self.state.apply(ob, item.key, now)
            if self.keys.robot_id_of(item.key) == ob.robot_id:
                self.observations.setdefault(ob.robot_id, deque(maxlen=OBSERVATIONS_KEPT)).append(ob)
        cam_items = self.cam_in.drain()
        for item in cam_items:  # decoded only when shown: most frames are never looked at
            rid = self.keys.robot_id_of(item.key)
            if rid is not None:
                self.frames.setdefault(rid, deque(maxlen=FRAMES_KEPT)).append((now, item.key, item.value))
        got = got or bool(obs_items) or bool(cam_items)
        if now >= self._next_state_s and self.state.version != self._published_version:
            self._published_version = self.state.version
            self.hub.publish_state(json.dumps(self.state.snapshot(), separators=(",", ":")))
            self._next_state_s = now + 1.0 / self.cfg.rate_hz
        if now >= self._next_cam_s:
            self._next_cam_s = now + 1.0 / self.cfg.camera_rate_hz
            for rid in self.hub.wanted_cameras():
                self._publish_camera(rid, now)
        return got

    def _publish_camera(self, rid: int, now: float) -> None:
        frames = self.frames.get(rid)
        if not frames:
            return
        settled = [f for f in frames if now - f[0] >= FRAME_SETTLE_S]
        _, key, payload = settled[-1] if settled else frames[0]
        try:
            img = codec.decode(m.CameraImage, payload)
        except codec.DecodeError as exc:
            self.rejects.reject(exc.kind, f"{key}: {exc.detail}")
            frames.clear()  # do not decode the same bad frame again
            return
        if not self._key_robot(key, img.robot_id):
            frames.clear()
            return
        if self._cam_sent.get(rid) == img.stamp_ns:
            return
        self._cam_sent[rid] = img.stamp_ns
        obs = [ob for ob in self.observations.get(rid, ())
               if ob.stamp_ns == img.stamp_ns and img.camera in ob.camera.split("+")]  # a rig joins names with +
        msg = camera_message(img, obs, self.cfg.scenario, self.cfg.thumb_width)
        self.hub.publish_camera(rid, json.dumps(msg, separators=(",", ":")))

    def run(self, stop_event: threading.Event) -> int:
        """Serve the page and follow the run until ``stop_event``."""
        self.server.start()
        log.info("view of run %r (scenario %s) at %s", self.cfg.run, self.cfg.scenario.name, self.url)
        while not stop_event.is_set():
            self.bus.wait(0.05)
            self.step()
        return 0

    def close(self) -> None:
        """Stop the web server (browsers see the WebSocket close and retry)."""
        self.server.close()


def main(argv: Sequence[str] | None = None) -> int:
    """Console entry for ``tagswarm view``."""
    return serve_node(PROG, lambda: build_config(argv), lambda _cfg: "view", ViewNode)


if __name__ == "__main__":
    raise SystemExit(main())

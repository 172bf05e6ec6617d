"""The live view's web side: the page's files, ``/state.json`` and the ``/ws`` WebSocket
on one port (the ``websockets`` library's threaded server), and the :class:`Hub` that
hands the loop thread's JSON to one sending thread per browser.  See
:mod:`tagswarm.view.view` for the page protocol."""

from __future__ import annotations

import http
import importlib.resources
import itertools
import json
import logging
import threading
from typing import Final

from websockets.datastructures import Headers
from websockets.exceptions import ConnectionClosed
from websockets.http11 import Request, Response
from websockets.sync.server import Server, ServerConnection, serve

from tagswarm.runtime.config import ConfigError

# every plain HTTP request (the page's files) ends the websockets handshake with a non-101
# answer, which that library logs at INFO: keep only its warnings
_ws_log = logging.getLogger("tagswarm.view.ws")
_ws_log.setLevel(logging.WARNING)

#: Files the page is made of (served from the package, never from the network).
STATIC: Final[dict[str, tuple[str, str]]] = {
    "/": ("index.html", "text/html; charset=utf-8"),
    "/index.html": ("index.html", "text/html; charset=utf-8"),
    "/app.js": ("app.js", "text/javascript; charset=utf-8"),
    "/style.css": ("style.css", "text/css; charset=utf-8"),
    "/favicon.svg": ("favicon.svg", "image/svg+xml"),
}
class Hub:
    """Hand-off between the loop thread (writer) and the per-browser threads (readers).

    Holds the newest state snapshot and camera thumbnails as ready-to-send JSON
    text with version numbers, and which robot each browser has selected.
    """

    def __init__(self, scene_json: str) -> None:
        self._cond = threading.Condition()
        self.scene_json = scene_json
        self._state: tuple[int, str] = (0, json.dumps({"type": "state", "robots": [], "version": 0}))
        self._thumbs: dict[int, tuple[int, str]] = {}
        self._selected: dict[int, int | None] = {}
        self._ids = itertools.count(1)
        self.closing = False
        self.sent_states = 0
        self.connections = 0

    # loop thread --------------------------------------------------------------
    def publish_state(self, text: str) -> None:
        with self._cond:
            self._state = (self._state[0] + 1, text)
            self._cond.notify_all()

    def publish_camera(self, robot_id: int, text: str) -> None:
        with self._cond:
            old = self._thumbs.get(robot_id, (0, ""))[0]
            self._thumbs[robot_id] = (old + 1, text)
            self._cond.notify_all()

    def wanted_cameras(self) -> set[int]:
        """Robots whose camera some connected browser shows."""
        with self._cond:
            return {r for r in self._selected.values() if r is not None}

    def close(self) -> None:
        with self._cond:
            self.closing = True
            self._cond.notify_all()

    # browser threads ----------------------------------------------------------
    def join(self) -> int:
        with self._cond:
            cid = next(self._ids)
            self._selected[cid] = None
            self.connections += 1
            return cid

    def leave(self, cid: int) -> None:
        with self._cond:
            self._selected.pop(cid, None)

    def select(self, cid: int, robot_id: int | None) -> None:
        with self._cond:
            if cid in self._selected:
                self._selected[cid] = robot_id

    def state(self) -> tuple[int, str]:
        with self._cond:
            return self._state

    def camera(self, robot_id: int | None) -> tuple[int, str] | None:
        with self._cond:
            return None if robot_id is None else self._thumbs.get(robot_id)

    def wait(self, timeout_s: float) -> None:
        """Block until something is published (or the timeout)."""
        with self._cond:
            self._cond.wait(timeout_s)


def _select_message(text: str | bytes) -> int | bool | None:
    """The robot of a ``select`` message from the page; ``False`` if it is not one (ignored)."""
    try:
        msg = json.loads(text)
    except (ValueError, UnicodeDecodeError):
        return False
    if not isinstance(msg, dict) or msg.get("type") != "select":
        return False
    robot = msg.get("robot")
    if robot is None:
        return None
    if isinstance(robot, int) and not isinstance(robot, bool) and 0 <= robot < 1_000_000:
        return robot
    return False


def serve_browser(conn: ServerConnection, hub: Hub) -> None:
    """One browser's WebSocket: scene once, then each new state and the selected camera."""
    cid = hub.join()
    try:
        conn.send(hub.scene_json)
        sent_state = -1
        sent_cam: tuple[int | None, int] = (None, -1)
        selected: int | None = None
        while not hub.closing:
            while True:  # the page's messages (camera selection); anything else is ignored
                try:
                    text = conn.recv(timeout=0)
                except TimeoutError:
                    break
                choice = _select_message(text)
                if choice is not False:
                    selected = choice if isinstance(choice, int) else None
                    hub.select(cid, selected)
            version, state = hub.state()
            if version != sent_state:
                conn.send(state)
                sent_state = version
                hub.sent_states += 1
            cam = hub.camera(selected)
            if cam is not None and (selected, cam[0]) != sent_cam:
                conn.send(cam[1])
                sent_cam = (selected, cam[0])
            hub.wait(0.1)
    except ConnectionClosed:
        pass
    finally:
        hub.leave(cid)


class WebServer:
    """HTTP (the page's files, ``/state.json``) and WebSocket (``/ws``) on one port."""

    def __init__(self, host: str, port: int, hub: Hub) -> None:
        self.hub = hub
        web = importlib.resources.files("tagswarm.view") / "web"
        self._files = {path: (web.joinpath(name).read_bytes(), ctype) for path, (name, ctype) in STATIC.items()}
        try:
            self._server: Server = serve(lambda conn: serve_browser(conn, hub), host, port,
                                         process_request=self._http, compression=None,
                                         logger=_ws_log)
        except OSError as exc:
            raise ConfigError(f"--host/--port: cannot listen on {host}:{port} ({exc.strerror or exc})") from None
        self.host, self.port = self._server.socket.getsockname()[:2]
        self._thread = threading.Thread(target=self._server.serve_forever, name="view-http", daemon=True)

    @property
    def url(self) -> str:
        return f"http://{self.host}:{self.port}/"

    def start(self) -> None:
        self._thread.start()

    def close(self) -> None:
        self.hub.close()
        self._server.shutdown()
        if self._thread.is_alive():
            self._thread.join(timeout=5)

    def _http(self, conn: ServerConnection, request: Request) -> Response | None:
        path = request.path.split("?", 1)[0]
        if path == "/ws":
            return None  # go on with the WebSocket handshake
        if path == "/state.json":
            return _response(200, self.hub.state()[1].encode(), "application/json")
        found = self._files.get(path)
        if found is None:
            return _response(404, b"not found\n", "text/plain; charset=utf-8")
        return _response(200, *found)


def _response(status: int, body: bytes, ctype: str) -> Response:
    headers = Headers([("Content-Type", ctype), ("Content-Length", str(len(body))), ("Cache-Control", "no-store"),
                       ("Connection", "close")])
    return Response(status, http.HTTPStatus(status).phrase, headers, body)

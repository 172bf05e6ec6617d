"""``tagswarm view`` in a real browser: headless Chromium (Debian's ``/usr/bin/chromium``)
driven by Playwright loads the view of a running ``tagswarm up`` (lockstep, paper
scenario) and the test checks what the page DRAWS against what the server published.

One scenario, in order: the page shows every robot's fused pose at the position the
server published with the same stamp (within 1 cm), read both from the SVG's ``data-x``/
``data-y`` and from the rendered geometry (the robot body's on-screen centre mapped back
to metres through the SVG's own screen transform); with the world held (the test is a
lockstep participant) at a step the server published its MAP for, every robot is drawn
at its map pose; garbage published on the map key is counted and the page keeps updating;
a screenshot goes to ``runs/ci-artifacts/view.png``; the system is restarted under the
view (new run id: the page starts over on the new run); the view itself is restarted (the
page reconnects).

Without a browser: ``tagswarm up --view PORT`` serves the page and the live state while it
runs, and stops the view (and exits) promptly at the end of the run.

The browser tests need Chromium and Playwright: when either is missing they are skipped
with the reason, except under CI (``CI`` set), where that fails them (and only them).
"""

from __future__ import annotations

import importlib
import json
import math
import os
import socket
import subprocess
import tempfile
import threading
import time
import urllib.request
from collections.abc import Callable, Iterator
from contextlib import contextmanager, suppress
from pathlib import Path
from types import ModuleType
from typing import Any

import pytest
from websockets.exceptions import ConnectionClosed
from websockets.sync.client import connect as ws_connect

from tagswarm.protocol import codec
from tagswarm.protocol import messages as m
from tagswarm.protocol.bus import Bus
from tagswarm.protocol.geometry import Pose2, se2_compose
from tagswarm.protocol.keys import Keys
from tagswarm.protocol.layout import arena_to_map
from tagswarm.protocol.scenario import load_scenario
from tagswarm.runtime import lockstep
from tests.harness import client, endpoint, free_port, script, stop

#: Debian's chromium (scripts/setup.sh installs it); VIEW_TEST_CHROMIUM points elsewhere (tests of the gate)
CHROMIUM = os.environ.get("VIEW_TEST_CHROMIUM", "/usr/bin/chromium")
ARTIFACTS = Path(__file__).resolve().parents[2] / "runs" / "ci-artifacts"
CHROMIUM_ARGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
                 "--disable-background-networking", "--disable-component-update", "--disable-sync"]
ROBOTS = 4
TOLERANCE_M = 0.01  # drawn vs published
#: The test joins the lockstep under this name, so that it can hold the world still at a map step.
TEST_PARTICIPANT = "test/0"
HOLD_MAX_S = 20.0  # a hold never outlasts this (the world's ack timeout is set above it)
ACK_TIMEOUT_S = 30.0


def browser_unavailable() -> str | None:
    """Why the browser tests cannot run here (None: they can)."""
    if not os.path.exists(CHROMIUM):
        return f"{CHROMIUM} is not installed (apt-get install chromium, or scripts/setup.sh as root)"
    try:
        importlib.import_module("playwright.sync_api")
    except ImportError as exc:
        return f"playwright is not importable ({exc}); pip install -e '.[dev]'"
    return None


@pytest.fixture
def sync_api() -> ModuleType:
    """Playwright's sync API; skips the test when there is no browser, but fails it under CI
    (``CI`` set), which installs one: a missing browser there must not pass silently."""
    why = browser_unavailable()
    if why is not None:
        if os.environ.get("CI"):
            pytest.fail(f"browser test cannot run under CI: {why}", pytrace=False)
        pytest.skip(why)
    return importlib.import_module("playwright.sync_api")


# What the page draws: one entry per robot, read in one go so that it is one moment.  Besides the
# data-* attributes, the position is read from the rendered geometry: the centre of the robot body's
# on-screen box (a rectangle centred on the pose: its box is centred there however it is rotated),
# mapped back through the SVG root's own screen transform (viewBox + preserveAspectRatio) to its user
# units, which the page declares in metres (x right, y down, arena frame mirrored).
READ_FUSED = """() => {
  const svg = document.getElementById('arena');
  const toUser = svg.getScreenCTM().inverse();
  return Array.from(svg.querySelectorAll('.robot-fused[data-stamp]'))
    .filter((g) => g.getAttribute('display') !== 'none')
    .map((g) => {
      const box = g.querySelector('rect.body').getBoundingClientRect();
      const c = new DOMPoint(box.left + box.width / 2, box.top + box.height / 2).matrixTransform(toUser);
      return {robot: Number(g.dataset.robot), x: Number(g.dataset.x), y: Number(g.dataset.y),
              stamp: Number(g.dataset.stamp), source: g.dataset.source, ux: c.x, uy: c.y,
              w: box.width, h: box.height};
    });
}"""


def _port_open(port: int) -> bool:
    with socket.socket() as s:
        s.settimeout(0.2)
        return s.connect_ex(("127.0.0.1", port)) == 0


def _wait(cond: Callable[[], bool], timeout_s: float, what: str, proc: subprocess.Popen[bytes] | None = None,
          log: Path | None = None) -> None:
    deadline = time.monotonic() + timeout_s
    while not cond():
        if proc is not None and proc.poll() is not None:
            raise AssertionError(f"{what}: process exited with {proc.returncode}\n"
                                 + (log.read_text(errors="replace")[-3000:] if log else ""))
        assert time.monotonic() < deadline, f"timed out waiting for {what}"
        time.sleep(0.1)  # polling a condition with a deadline, not a fixed sleep


@contextmanager
def _proc(argv: list[str], log: Path) -> Iterator[subprocess.Popen[bytes]]:
    with open(log, "wb") as fh:
        proc = subprocess.Popen(argv, stdout=fh, stderr=subprocess.STDOUT, env=dict(os.environ, PYTHONUNBUFFERED="1"))
        try:
            yield proc
        finally:
            stop(proc)


def _up_argv(ep: str, run: str, out: Path) -> list[str]:
    """A lockstep run of the paper scenario in which the test is a participant too."""
    participants = [*(f"agent/{r}" for r in range(ROBOTS)), "server/0", TEST_PARTICIPANT]
    return [script("tagswarm"), "up", "--clock", "lockstep", "--seed", "1", "--duration", "600", "--listen", ep,
            "--run", run, "--out", str(out), "--no-live", "--no-report",
            "--set", f"clock.participants={json.dumps(participants)}",
            "--set", f"clock.ack_timeout_s={ACK_TIMEOUT_S}"]


def _view_argv(ep: str, run: str, port: int) -> list[str]:
    return [script("tagswarm"), "view", "--connect", ep, "--run", run, "--port", str(port)]


class Published:
    """What the server published (map entries and corrections) by (source, robot, stamp)."""

    def __init__(self, bus: Bus, keys: Keys) -> None:
        self.bus = bus
        self.maps = bus.subscribe(keys.map())
        self.corrections = bus.subscribe(keys.correction())
        self.poses: dict[tuple[str, int, int], tuple[float, float]] = {}

    def poll(self) -> None:
        for item in self.maps.drain():
            with suppress(codec.DecodeError):  # the test's own garbage comes back here too
                g = codec.decode(m.GlobalMap, item.value)
                for e in g.robots:
                    self.poses[("map", e.robot_id, g.stamp_ns)] = (e.x_m, e.y_m)
        for item in self.corrections.drain():
            c = codec.decode(m.Correction, item.value)
            if c.localised:
                self.poses[("correction", c.robot_id, c.stamp_ns)] = (c.x_m, c.y_m)

    def clear(self) -> None:
        """Forget everything (a new run reuses the same stamps)."""
        self.poll()
        self.poses.clear()

    def newest_after_now(self, timeout_s: float = 30.0) -> int:
        """Stamp of a correction that arrives from now on: once the test's own subscription gets
        the server's messages (peers find each other by gossip), everything newer is comparable."""
        self.poll()
        known = set(self.poses)

        def fresh() -> bool:
            self.poll()
            return any(k[0] == "correction" and k not in known for k in self.poses)

        assert self.bus.wait_for(fresh, timeout_s), "the test never received a correction"
        return max(k[2] for k in self.poses if k[0] == "correction" and k not in known)

    def lookup(self, drawn: dict[str, Any]) -> tuple[float, float] | None:
        self.poll()
        return self.poses.get((drawn["source"], drawn["robot"], drawn["stamp"]))


class Participant(threading.Thread):
    """The test as the lockstep participant ``test/0``, on its own session and thread.

    It acknowledges every tick at once, so the run goes on as usual, except that
    :meth:`held_at_map` holds the world still at the next step the server published its
    map for: the server publishes a step's corrections and map before it acknowledges the
    step, so once its ack of step N is in, a map stamped with tick N's time is there or
    there is none for that step.  Until the test acknowledges that step the world waits, so
    what the page draws settles on exactly that map (on equal stamps the view shows the
    map's copy of an estimate).
    """

    def __init__(self, ep: str, keys: Keys) -> None:
        super().__init__(name="test-participant", daemon=True)
        self.ep, self.keys = ep, keys
        self.ready = threading.Event()
        self._want = threading.Event()
        self._held = threading.Event()
        self._release = threading.Event()
        self._quit = threading.Event()
        self.held_map: m.GlobalMap | None = None
        self.error: BaseException | None = None

    def run(self) -> None:
        try:
            with client(self.ep) as bus:
                self._serve(bus)
        except BaseException as exc:  # reported by held_at_map / stop
            self.error = exc
            self.ready.set()

    def _serve(self, bus: Bus) -> None:
        ticks = bus.subscribe(self.keys.tick())
        maps = bus.subscribe(self.keys.map())
        server_acks = bus.subscribe(self.keys.ack("server/0"))
        bus.declare_token(self.keys.alive(TEST_PARTICIPANT))
        me = lockstep.Participant(bus, self.keys, TEST_PARTICIPANT)
        self.ready.set()
        by_stamp: dict[int, m.GlobalMap] = {}
        server_steps: set[int] = set()

        def absorb() -> None:
            for item in maps.drain():
                with suppress(codec.DecodeError):  # the test's garbage on the map key
                    g = codec.decode(m.GlobalMap, item.value)
                    by_stamp[g.stamp_ns] = g
            for item in server_acks.drain():
                server_steps.add(codec.decode(m.TickAck, item.value).step)

        while not self._quit.is_set():
            bus.wait_for(lambda: len(ticks) > 0 or self._quit.is_set(), 0.5)
            if not self._want.is_set():  # only what arrives while a hold is wanted counts (runs reuse stamps)
                maps.drain()
                server_acks.drain()
                by_stamp.clear()
                server_steps.clear()
            for item in ticks.drain():
                tick = codec.decode(m.Tick, item.value)
                if self._want.is_set():

                    def published(step: int = tick.step) -> bool:
                        absorb()
                        return step in server_steps or self._quit.is_set()

                    bus.wait_for(published, 10.0)
                    g = by_stamp.get(tick.stamp_ns)
                    if g is not None and len(g.robots) >= ROBOTS:
                        self.held_map = g
                        self._want.clear()
                        self._held.set()
                        self._release.wait(HOLD_MAX_S)
                        self._release.clear()
                        self._held.clear()
                        by_stamp.clear()
                        server_steps.clear()
                me.ack(tick)

    @contextmanager
    def held_at_map(self, timeout_s: float = 30.0) -> Iterator[m.GlobalMap]:
        """Hold the world at the next map step (see the class docstring); yields that map."""
        self._want.set()
        deadline = time.monotonic() + timeout_s
        while not self._held.wait(0.1):
            assert self.error is None, f"participant thread failed: {self.error!r}"
            assert time.monotonic() < deadline, "the world never reached a step with a map of every robot"
        t0 = time.monotonic()
        try:
            assert self.held_map is not None
            yield self.held_map
        finally:
            self._release.set()
        assert time.monotonic() - t0 < HOLD_MAX_S, "the check outlasted the hold: the world may have moved on"

    def stop(self) -> None:
        self._quit.set()
        self._release.set()
        self.join(timeout=10)
        assert self.error is None, f"participant thread failed: {self.error!r}"


def _geometry_in_map(d: dict[str, Any], a2m: Pose2) -> tuple[float, float]:
    """Where the page put a robot's body on screen, in the map frame: user units are metres with
    y down (the arena frame mirrored), and T_map_arena is the scenario's."""
    x, y, _ = se2_compose(a2m, (d["ux"], -d["uy"], 0.0))
    return x, y


class Errors:
    """Largest drawn-vs-published distances seen, for the log."""

    def __init__(self) -> None:
        self.data_m = 0.0
        self.geometry_m = 0.0
        self.compared = 0
        self.against_map: dict[int, int] = {}

    def check(self, d: dict[str, Any], ref: tuple[float, float], a2m: Pose2, *, is_map: bool) -> None:
        e_data = math.hypot(d["x"] - ref[0], d["y"] - ref[1])
        gx, gy = _geometry_in_map(d, a2m)
        e_geom = math.hypot(gx - ref[0], gy - ref[1])
        assert e_data < TOLERANCE_M, f"robot {d['robot']}: data-x/y {d['x']:.4f},{d['y']:.4f} vs published {ref}"
        assert e_geom < TOLERANCE_M, f"robot {d['robot']}: drawn at {gx:.4f},{gy:.4f} (map frame) vs published {ref}"
        assert d["w"] > 1 and d["h"] > 1, d  # a body that is actually drawn (a few pixels at least)
        self.data_m, self.geometry_m = max(self.data_m, e_data), max(self.geometry_m, e_geom)
        self.compared += 1
        if is_map:
            self.against_map[d["robot"]] = self.against_map.get(d["robot"], 0) + 1


def _check_drawn_against_published(page: Any, pub: Published, reads: int, a2m: Pose2, errs: Errors) -> None:
    """Compare ``reads`` DOM reads of the moving system with what was published with the same stamp."""
    stamps: list[int] = []
    since = pub.newest_after_now()
    # every robot localised, and drawn from messages the test has received too
    page.wait_for_function(f"(() => {{ const d = ({READ_FUSED})(); "
                           f"return d.length >= {ROBOTS} && Math.min(...d.map((r) => r.stamp)) >= {since}; }})()",
                           timeout=30_000)
    for _ in range(reads):
        seen = page.evaluate("Number(document.body.dataset.states)")
        page.wait_for_function(f"Number(document.body.dataset.states) > {seen}")
        drawn = page.evaluate(READ_FUSED)
        assert sorted(d["robot"] for d in drawn) == list(range(ROBOTS)), drawn
        stamps.append(min(d["stamp"] for d in drawn))
        for d in drawn:
            # the test's own subscription may get the message a moment after the view did
            assert pub.bus.wait_for(lambda d=d: pub.lookup(d) is not None, 5.0), \
                f"no published {d['source']} of robot {d['robot']} with stamp {d['stamp']}"
            errs.check(d, pub.poses[(d["source"], d["robot"], d["stamp"])], a2m, is_map=d["source"] == "map")
    assert stamps[-1] > stamps[0], stamps  # the page moves on with the system


def _check_drawn_against_map(page: Any, part: Participant, a2m: Pose2, errs: Errors) -> None:
    """With the world held at a step the server published its map for, every robot is drawn
    where that map puts it."""
    before = dict(errs.against_map)
    with part.held_at_map() as g:
        want = {e.robot_id: (e.x_m, e.y_m) for e in g.robots}
        assert sorted(want) == list(range(ROBOTS)), want
        page.wait_for_function(
            f"(() => {{ const d = ({READ_FUSED})(); return d.length === {ROBOTS} && "
            f"d.every((r) => r.stamp === {g.stamp_ns} && r.source === 'map'); }})()", timeout=15_000)
        drawn = page.evaluate(READ_FUSED)
        assert sorted(d["robot"] for d in drawn) == list(range(ROBOTS)), drawn
        for d in drawn:
            assert d["stamp"] == g.stamp_ns and d["source"] == "map", d
            errs.check(d, want[d["robot"]], a2m, is_map=True)
    assert all(errs.against_map.get(r, 0) > before.get(r, 0) for r in range(ROBOTS)), errs.against_map


def _scenario_a2m(run_folder: Path) -> Pose2:
    """T_map_arena of the scenario ``up`` resolved (it writes it first thing)."""
    path = run_folder / "scenario.json"
    _wait(lambda: path.exists() and path.stat().st_size > 0, 20, f"{path}")
    return arena_to_map(load_scenario(str(path)))


def test_browser_view_of_a_running_system(tmp_path: Path, sync_api: ModuleType) -> None:
    ep, run, http_port = endpoint(), f"view{os.getpid()}", free_port()
    keys = Keys(run)
    url = f"http://127.0.0.1:{http_port}/"
    errs = Errors()
    part = Participant(ep, keys)
    part.start()
    assert part.ready.wait(20) and part.error is None, part.error
    with tempfile.TemporaryDirectory() as profile, sync_api.sync_playwright() as pw, client(ep) as bus:
        with _proc(_up_argv(ep, run, tmp_path / "run1"), tmp_path / "up1.log") as up1:
            a2m = _scenario_a2m(tmp_path / "run1")
            with _proc(_view_argv(ep, run, http_port), tmp_path / "view1.log") as view1:
                _wait(lambda: _port_open(http_port), 20, "the view's HTTP port", view1, tmp_path / "view1.log")
                pub = Published(bus, keys)
                browser = pw.chromium.launch_persistent_context(
                    profile, executable_path=CHROMIUM, args=CHROMIUM_ARGS, headless=True,
                    viewport={"width": 1400, "height": 860})
                try:
                    page = browser.new_page()
                    errors: list[str] = []
                    page.on("pageerror", lambda exc: errors.append(str(exc)))
                    page.goto(url)
                    # the geometry read relies on how the page scales its arena
                    assert page.evaluate("document.getElementById('arena').getAttribute('preserveAspectRatio')") \
                        == "xMidYMid meet"
                    # 1. every robot drawn, at the published pose with the same stamp; at the map's pose
                    page.wait_for_function(f"document.querySelectorAll('#arena .robot-fused[data-stamp]').length "
                                           f">= {ROBOTS} && Number(document.body.dataset.cameras || 0) >= 2",
                                           timeout=40_000)
                    _check_drawn_against_published(page, pub, 8, a2m, errs)
                    assert errs.compared == 8 * ROBOTS
                    _check_drawn_against_map(page, part, a2m, errs)
                    run1 = page.evaluate("document.body.dataset.runId")
                    assert run1.startswith(f"{run}-")
                    assert page.locator("#cam-overlay polygon").count() >= 1  # robot 0 sees the others' tags

                    # 2. garbage on the map key: counted, and the page keeps updating
                    for payload in (b"\xc1not msgpack", b"", codec.encode(m.Tick(
                            seq=0, stamp_ns=1, run_id="x", step=0, dt_ns=1, mode="lockstep"))):
                        bus.put(keys.map(), payload)
                    page.wait_for_function("document.getElementById('net').textContent.includes('malformed 3')",
                                           timeout=10_000)
                    _check_drawn_against_published(page, pub, 3, a2m, errs)
                    # a screenshot for people (CI keeps runs/ci-artifacts), once the robots have moved a little
                    page.wait_for_function("Number(document.body.dataset.simNs) > 6e9", timeout=30_000)
                    ARTIFACTS.mkdir(parents=True, exist_ok=True)
                    page.screenshot(path=str(ARTIFACTS / "view.png"))
                    assert (ARTIFACTS / "view.png").stat().st_size > 20_000

                    # 3. the system restarts under the view: a new run id, the page starts over
                    stop(up1)
                    pub.clear()
                    with _proc(_up_argv(ep, run, tmp_path / "run2"), tmp_path / "up2.log") as up2:
                        page.wait_for_function(
                            f"document.body.dataset.runId && document.body.dataset.runId !== '{run1}' && "
                            f"document.querySelectorAll('#arena .robot-fused[data-stamp]').length >= {ROBOTS}",
                            timeout=40_000)
                        assert up2.poll() is None
                        run2 = page.evaluate("document.body.dataset.runId")
                        assert run2.startswith(f"{run}-") and page.evaluate("Number(document.body.dataset.epoch)") >= 1
                        _check_drawn_against_published(page, pub, 3, a2m, errs)
                        _check_drawn_against_map(page, part, a2m, errs)

                        # 4. the view restarts: the page reconnects on its own
                        stop(view1)
                        page.wait_for_function("document.body.dataset.connected === '0'", timeout=10_000)
                        with _proc(_view_argv(ep, run, http_port), tmp_path / "view2.log"):
                            page.wait_for_function(
                                "document.body.dataset.connected === '1' && Number(document.body.dataset.connects) >= 2"
                                f" && document.body.dataset.runId === '{run2}'", timeout=30_000)
                            _check_drawn_against_published(page, pub, 3, a2m, errs)
                            _check_drawn_against_map(page, part, a2m, errs)
                    assert not errors, errors
                    print(f"compared {errs.compared} drawn poses, {sum(errs.against_map.values())} against the map "
                          f"({errs.against_map}); max error {errs.data_m * 1000:.3f} mm (data-x/y), "
                          f"{errs.geometry_m * 1000:.3f} mm (rendered geometry)")
                finally:
                    browser.close()
                    part.stop()


def _get(url: str) -> tuple[int, str, str]:
    with urllib.request.urlopen(url, timeout=10) as r:
        return r.status, r.headers.get("Content-Type", ""), r.read().decode()


def test_up_view_serves_the_run_and_stops_with_it(tmp_path: Path) -> None:
    """``tagswarm up --view PORT``: the page, its state over HTTP and the WebSocket while the run
    goes on; at the end the view is stopped at once (it never ends on its own) and up exits 0."""
    port, out, duration_s, run = free_port(), tmp_path / "run", 8, f"upview{os.getpid()}"
    argv = [script("tagswarm"), "up", "--clock", "lockstep", "--seed", "2", "--robots", "2", "--duration",
            str(duration_s), "--run", run, "--no-live", "--no-report", "--out", str(out), "--view", str(port)]
    states: list[tuple[float, dict[str, Any]]] = []
    closed_at = None
    with _proc(argv, tmp_path / "up.log") as up:
        _wait(lambda: _port_open(port), 30, "the view's HTTP port", up, tmp_path / "up.log")
        status, ctype, html = _get(f"http://127.0.0.1:{port}/")
        assert status == 200 and ctype.startswith("text/html") and '<svg id="arena"' in html and "app.js" in html
        assert "robot-fused" in _get(f"http://127.0.0.1:{port}/app.js")[2]
        with ws_connect(f"ws://127.0.0.1:{port}/ws", open_timeout=10) as ws:
            scene = json.loads(ws.recv(timeout=10))
            assert scene["type"] == "scene" and scene["robot_ids"] == [0, 1] and scene["scenario"] == "paper"
            deadline = time.monotonic() + 120
            mid: dict[str, Any] | None = None
            try:
                while time.monotonic() < deadline:
                    msg = json.loads(ws.recv(timeout=30))
                    if msg["type"] == "state" and "sim_ns" in msg:  # not the placeholder before any data
                        states.append((time.monotonic(), msg))
                        if mid is None and msg["sim_ns"] > 1e9:  # the same state over plain HTTP, mid-run
                            mid = json.loads(_get(f"http://127.0.0.1:{port}/state.json")[2])
                            assert mid["sim_ns"] >= msg["sim_ns"] and [r["id"] for r in mid["robots"]] == [0, 1]
            except ConnectionClosed:  # the view stopped: the run is over
                closed_at = time.monotonic()
        assert mid is not None
        rc = up.wait(timeout=60)
        exited_at = time.monotonic()
    assert rc == 0, (tmp_path / "up.log").read_text()[-3000:]
    assert closed_at is not None, "the view's WebSocket never closed"
    sims = [s["sim_ns"] for _, s in states]
    assert sims == sorted(sims) and len(set(sims)) >= 10, sims  # simulation time advancing on the page
    last = states[-1][1]
    assert last["sim_ns"] >= (duration_s - 0.1) * 1e9 and last["clock"] == "lockstep"  # the view saw the end
    assert [r["id"] for r in last["robots"]] == [0, 1]
    for r in last["robots"]:
        assert r["truth"] is not None and r["fused"] is not None and r["error_m"] < 0.5, r
    assert last["run"] == run and last["run_id"].startswith(f"{run}-")
    # promptly: up used to wait its whole 5 s shutdown allowance for the view to end by itself
    ended_at = min(t for t, s in states if s["sim_ns"] == last["sim_ns"])
    print(f"up exited {exited_at - ended_at:.2f} s after the last tick was shown "
          f"(WebSocket closed after {closed_at - ended_at:.2f} s)")
    assert exited_at - ended_at < 5.0
    assert json.loads((out / "run.json").read_text())["exit_codes"]["view"] == 0  # stopped cleanly, not killed

"""``tagswarm view`` in a real browser: headless Chromium (Debian's ``/usr/bin/chromium``)
driven by Playwright loads the view of a running ``tagswarm up`` (lockstep, paper
scenario) and the test checks what the page DRAWS against what the server published.

One scenario, in order: the page shows every robot's fused pose at the position the
server published with the same stamp (within 1 cm); garbage published on the map key
is counted and the page keeps updating; a screenshot goes to
``runs/ci-artifacts/view.png``; the system is restarted under the view (new run id: the page
starts over on the new run); the view itself is restarted (the page reconnects).
"""

from __future__ import annotations

import math
import os
import signal
import socket
import subprocess
import tempfile
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager, suppress
from pathlib import Path
from typing import Any

import pytest

from protocol import codec
from protocol import messages as m
from protocol.bus import Bus
from protocol.keys import Keys
from tests.harness import client, endpoint, free_port, script

CHROMIUM = "/usr/bin/chromium"
ARTIFACTS = Path(__file__).resolve().parents[2] / "runs" / "ci-artifacts"
CHROMIUM_ARGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
                 "--disable-background-networking", "--disable-component-update", "--disable-sync"]
ROBOTS = 4

if not os.path.exists(CHROMIUM):
    if os.environ.get("CI"):  # CI installs it (scripts/setup.sh): a missing browser there is a failure
        pytest.fail(f"{CHROMIUM} is missing: scripts/setup.sh should have installed Debian's chromium",
                    pytrace=False)
    pytest.skip(f"{CHROMIUM} is not installed (apt-get install chromium)", allow_module_level=True)

sync_api = pytest.importorskip("playwright.sync_api")

# what the page draws: one entry per robot, read in one go so that it is one moment
READ_FUSED = """() => Array.from(document.querySelectorAll('#arena .robot-fused[data-stamp]'))
  .filter((g) => g.getAttribute('display') !== 'none')
  .map((g) => ({robot: Number(g.dataset.robot), x: Number(g.dataset.x), y: Number(g.dataset.y),
                stamp: Number(g.dataset.stamp), source: g.dataset.source}))"""


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
            _stop(proc)


def _stop(proc: subprocess.Popen[bytes]) -> None:
    if proc.poll() is None:
        proc.send_signal(signal.SIGINT)
        try:
            proc.wait(timeout=30)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()


def _up_argv(ep: str, run: str, out: Path) -> list[str]:
    return [script("tagswarm"), "up", "--clock", "lockstep", "--seed", "1", "--duration", "600", "--listen", ep,
            "--run", run, "--out", str(out), "--no-live", "--no-report"]


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


def _check_drawn_against_published(page: Any, pub: Published, reads: int) -> tuple[int, int]:
    """Compare ``reads`` DOM reads with the published poses; returns (compared, from the map)."""
    compared = from_map = 0
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
            x, y = pub.poses[(d["source"], d["robot"], d["stamp"])]
            assert math.hypot(d["x"] - x, d["y"] - y) < 0.01, (d, (x, y))
            compared += 1
            from_map += d["source"] == "map"
    assert stamps[-1] > stamps[0], stamps  # the page moves on with the system
    return compared, from_map


def test_browser_view_of_a_running_system(tmp_path: Path) -> None:
    ep, run, http_port = endpoint(), f"view{os.getpid()}", free_port()
    keys = Keys(run)
    url = f"http://127.0.0.1:{http_port}/"
    with tempfile.TemporaryDirectory() as profile, sync_api.sync_playwright() as pw, client(ep) as bus:
        with _proc(_up_argv(ep, run, tmp_path / "run1"), tmp_path / "up1.log") as up1:
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
                    # 1. every robot drawn, at the published pose with the same stamp
                    page.wait_for_function(f"document.querySelectorAll('#arena .robot-fused[data-stamp]').length "
                                           f">= {ROBOTS} && Number(document.body.dataset.cameras || 0) >= 2",
                                           timeout=40_000)
                    compared, from_map = _check_drawn_against_published(page, pub, reads=8)
                    assert compared == 8 * ROBOTS
                    run1 = page.evaluate("document.body.dataset.runId")
                    assert run1.startswith(f"{run}-")
                    assert page.locator("#cam-overlay polygon").count() >= 1  # robot 0 sees the others' tags

                    # 2. garbage on the map key: counted, and the page keeps updating
                    for payload in (b"\xc1not msgpack", b"", codec.encode(m.Tick(
                            seq=0, stamp_ns=1, run_id="x", step=0, dt_ns=1, mode="lockstep"))):
                        bus.put(keys.map(), payload)
                    page.wait_for_function("document.getElementById('net').textContent.includes('malformed 3')",
                                           timeout=10_000)
                    _check_drawn_against_published(page, pub, reads=3)
                    # a screenshot for people (CI keeps runs/ci-artifacts), once the robots have moved a little
                    page.wait_for_function("Number(document.body.dataset.simNs) > 6e9", timeout=30_000)
                    ARTIFACTS.mkdir(parents=True, exist_ok=True)
                    page.screenshot(path=str(ARTIFACTS / "view.png"))
                    assert (ARTIFACTS / "view.png").stat().st_size > 20_000

                    # 3. the system restarts under the view: a new run id, the page starts over
                    _stop(up1)
                    pub.clear()
                    with _proc(_up_argv(ep, run, tmp_path / "run2"), tmp_path / "up2.log") as up2:
                        page.wait_for_function(
                            f"document.body.dataset.runId && document.body.dataset.runId !== '{run1}' && "
                            f"document.querySelectorAll('#arena .robot-fused[data-stamp]').length >= {ROBOTS}",
                            timeout=40_000)
                        assert up2.poll() is None
                        run2 = page.evaluate("document.body.dataset.runId")
                        assert run2.startswith(f"{run}-") and page.evaluate("Number(document.body.dataset.epoch)") >= 1
                        _check_drawn_against_published(page, pub, reads=3)

                        # 4. the view restarts: the page reconnects on its own
                        _stop(view1)
                        page.wait_for_function("document.body.dataset.connected === '0'", timeout=10_000)
                        with _proc(_view_argv(ep, run, http_port), tmp_path / "view2.log"):
                            page.wait_for_function(
                                "document.body.dataset.connected === '1' && Number(document.body.dataset.connects) >= 2"
                                f" && document.body.dataset.runId === '{run2}'", timeout=30_000)
                            _check_drawn_against_published(page, pub, reads=3)
                    assert not errors, errors
                    print(f"compared {compared} drawn poses ({from_map} from the map, the rest from corrections)")
                finally:
                    browser.close()

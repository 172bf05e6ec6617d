"""Helpers for tests that start real processes on a private loopback Zenoh network."""

from __future__ import annotations

import itertools
import json
import os
import signal
import socket
import subprocess
import sys
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path

from tagswarm.protocol import codec
from tagswarm.protocol import messages as m
from tagswarm.protocol.bus import Bus, BusConfig, open_bus
from tagswarm.protocol.keys import Keys
from tagswarm.runtime import lockstep

BIN = Path(sys.executable).parent


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def endpoint() -> str:
    return f"tcp/127.0.0.1:{free_port()}"


def script(name: str) -> str:
    """Path of an installed console script (what compose runs)."""
    path = BIN / name
    assert path.exists(), f"{name} is not installed in {BIN}; run pip install -e ."
    return str(path)


def stop(proc: subprocess.Popen[bytes], sig: int = signal.SIGINT, timeout_s: float = 30.0) -> None:
    """Send ``sig`` to a still running child (SIGINT: as Ctrl-C, so ``tagswarm up`` still writes
    its report), SIGKILL it after ``timeout_s``, and reap it."""
    if proc.poll() is None:
        proc.send_signal(sig)
        try:
            proc.wait(timeout=timeout_s)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()


@contextmanager
def process(argv: list[str], log: Path | None = None) -> Iterator[subprocess.Popen[bytes]]:
    """Run a child process; SIGTERM then SIGKILL it on exit."""
    out = open(log, "wb") if log else subprocess.DEVNULL
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    proc = subprocess.Popen(argv, stdout=out, stderr=subprocess.STDOUT, env=env)
    try:
        yield proc
    finally:
        stop(proc, signal.SIGTERM, 10.0)
        if log:
            out.close()  # type: ignore[union-attr]


def world_argv(ep: str, run: str, *overrides: str, extra: tuple[str, ...] = ()) -> list[str]:
    argv = [script("tagswarm-world"), "--listen", ep, "--run", run, "--log-level", "INFO", *extra]
    for o in overrides:
        argv += ["--set", o]
    return argv


@contextmanager
def client(ep: str) -> Iterator[Bus]:
    with open_bus(BusConfig(connect=(ep,))) as bus:
        yield bus


class Participant:
    """A lockstep participant run inside the test: acks every tick after calling
    ``on_tick(tick)`` (which may publish commands), with the runtime's participant."""

    def __init__(self, bus: Bus, keys: Keys, name: str) -> None:
        self.bus, self.keys, self.name = bus, keys, name
        self.ticks = bus.subscribe(keys.tick())
        self.lockstep = lockstep.Participant(bus, keys, name)
        bus.declare_token(keys.alive(name))

    def ack(self, tick: m.Tick) -> None:
        self.lockstep.ack(tick)

    def serve(self, on_tick: Callable[[m.Tick], bool], timeout_s: float = 120.0) -> None:
        """Handle ticks until ``on_tick`` returns False (that tick is not acked, nor any after it)."""
        done = False

        def work(tick: m.Tick) -> bool:
            nonlocal done
            done = not on_tick(tick)
            return not done

        def step() -> bool:
            ticks = (codec.decode(m.Tick, item.value) for item in self.ticks.drain())
            self.lockstep.serve(itertools.takewhile(lambda _: not done, ticks), work)
            return done

        assert self.bus.wait_for(step, timeout_s), "world stopped ticking"


def wait_alive(bus: Bus, keys: Keys, participant: str, timeout_s: float = 20.0) -> None:
    """Block until ``participant``'s liveliness token is visible.  Its subscribers
    were declared before the token, so after this our puts reach them."""
    changes = bus.watch_liveliness(keys.alive(participant))
    seen = False

    def up() -> bool:
        nonlocal seen
        seen = seen or any(c.value for c in changes.drain())
        return seen

    assert bus.wait_for(up, timeout_s), f"{participant} never came up"


def paper_counters(out: Path, duration_s: float, *extra: str) -> dict[str, dict[str, int]]:
    """``tagswarm up`` of the paper scenario (lockstep, seed 0) into ``out``; its counters per process."""
    res = subprocess.run([script("tagswarm"), "up", "--scenario", "paper", "--clock", "lockstep", "--seed", "0",
                          "--duration", str(duration_s), "--out", str(out), "--no-live", *extra],
                         capture_output=True, text=True, timeout=1200)
    assert res.returncode == 0, res.stdout[-3000:] + res.stderr[-3000:]
    counters: dict[str, dict[str, int]] = json.loads((out / "run.json").read_text())["counters"]
    return counters


def agents_total(counters: dict[str, dict[str, int]], name: str) -> int:
    """Counter ``name`` summed over every agent."""
    return sum(c.get(name, 0) for who, c in counters.items() if who.startswith("agent/"))

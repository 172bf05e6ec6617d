"""Children in their own process groups, and three nets that take every one of them down.

Each child starts in a new session (``start_new_session``), so it leads its own process
group: signals go to the whole group (the world's render workers with the world), a
Ctrl-C in the terminal reaches only the owner (which then tears down in order),
and killing the group leaves nothing behind.  Nets, from first to last:

1. the owner (the fixture's teardown, a ``with`` block, ``tagswarm up`` at the end of a
   run) stops its groups: SIGCONT, SIGTERM, a grace period, SIGKILL (:meth:`Child.stop`);
2. ``atexit`` and (unless the owner handles SIGTERM itself, ``catch_term=False``) a
   SIGTERM handler in the owner kill every group still alive;
3. a reaper process (:mod:`tagswarm.runtime.reaper`) holds the read end of a pipe and
   kills the groups it was told about when the owner is gone, however it ended
   (SIGKILL, pytest-timeout's ``os._exit``).
"""

from __future__ import annotations

import atexit
import logging
import os
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Mapping, Sequence
from pathlib import Path
from types import FrameType
from typing import IO, Any

log = logging.getLogger("tagswarm.runtime.procgroup")
REAPER = Path(__file__).with_name("reaper.py")


def group_alive(pgid: int) -> bool:
    """Whether any process (a zombie too) is left in process group ``pgid``."""
    try:
        os.killpg(pgid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def signal_group(pgid: int, sig: int) -> None:
    """Send ``sig`` to every process of group ``pgid``; a group already gone is fine."""
    try:
        os.killpg(pgid, sig)
    except ProcessLookupError:
        pass


class _Registry:
    """Every live group of this process, for the atexit/SIGTERM net and the reaper."""

    def __init__(self) -> None:
        self.groups: set[int] = set()
        self.lock = threading.Lock()
        self.reaper: subprocess.Popen[bytes] | None = None
        self.pid = os.getpid()
        self.hooked = False
        self.catch_term = True  # False: the owner's own SIGTERM handler stops its children
        self.previous_term: Any = None

    def _tell(self, line: str) -> None:
        if self.reaper is None or self.reaper.poll() is not None or self.pid != os.getpid():
            # a fork of the owner (multiprocessing) must not share our reaper's pipe
            self.reaper = subprocess.Popen([sys.executable, str(REAPER)], stdin=subprocess.PIPE,
                                           stdout=subprocess.DEVNULL, start_new_session=True)
            self.pid = os.getpid()
            for pgid in self.groups:
                self._write(f"+{pgid}\n")
        self._write(line)

    def _write(self, line: str) -> None:
        stdin: IO[bytes] | None = self.reaper.stdin if self.reaper is not None else None
        if stdin is None:
            return
        try:
            stdin.write(line.encode())
            stdin.flush()
        except (BrokenPipeError, ValueError):
            log.warning("the stray-process reaper is gone; teardown and atexit still stop the swarm")

    def add(self, pgid: int) -> None:
        with self.lock:
            self._hook()
            self.groups.add(pgid)
            self._tell(f"+{pgid}\n")

    def remove(self, pgid: int) -> None:
        with self.lock:
            if pgid in self.groups:
                self.groups.discard(pgid)
                self._write(f"-{pgid}\n")

    def kill_all(self) -> None:
        """SIGKILL every group still registered (atexit, SIGTERM): no grace, the process is ending."""
        for pgid in list(self.groups):
            signal_group(pgid, signal.SIGKILL)
            self.groups.discard(pgid)

    def _hook(self) -> None:
        if self.hooked:
            return
        self.hooked = True
        atexit.register(self.kill_all)
        if self.catch_term and threading.current_thread() is threading.main_thread():
            self.previous_term = signal.getsignal(signal.SIGTERM)
            signal.signal(signal.SIGTERM, self._on_term)

    def _on_term(self, signum: int, frame: FrameType | None) -> None:
        self.kill_all()
        previous = self.previous_term
        if callable(previous):
            previous(signum, frame)
            return
        # default action: die of SIGTERM as if we had never caught it
        signal.signal(signal.SIGTERM, signal.SIG_DFL if previous in (None, signal.SIG_DFL) else previous)
        os.kill(os.getpid(), signal.SIGTERM)


REGISTRY = _Registry()


class Child:
    """One child process, leader of its own process group, with its output in ``log``."""

    def __init__(self, name: str, argv: Sequence[str], log_path: Path, env: Mapping[str, str]) -> None:
        self.name, self.argv, self.log_path = name, list(argv), log_path
        self.signalled = False  # the test sent it a signal: whatever it exits with is expected
        self._fh = open(log_path, "wb")
        try:
            self.proc = subprocess.Popen(self.argv, stdout=self._fh, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL,
                                         env=dict(env), start_new_session=True)
        except OSError:
            self._fh.close()
            raise
        self.pgid = self.proc.pid  # a session leader's group id is its pid
        REGISTRY.add(self.pgid)

    @property
    def pid(self) -> int:
        return self.proc.pid

    def poll(self) -> int | None:
        return self.proc.poll()

    def send(self, sig: int) -> None:
        """Signal the whole group (the world's render workers with the world)."""
        self.signalled = True
        signal_group(self.pgid, sig)

    def stop(self, grace_s: float = 5.0) -> None:
        """End the group: SIGCONT (a frozen process could not act on SIGTERM), SIGTERM, then
        SIGKILL after ``grace_s`` or once the leader is gone; returns when the group is empty."""
        if self.proc.poll() is None:
            self.signalled = True
            signal_group(self.pgid, signal.SIGCONT)
            signal_group(self.pgid, signal.SIGTERM)
            try:
                self.proc.wait(timeout=grace_s)
            except subprocess.TimeoutExpired:
                pass
        self.reap()

    def reap(self, timeout_s: float = 10.0) -> None:
        """SIGKILL whatever is left of the group and wait until it is empty."""
        signal_group(self.pgid, signal.SIGKILL)
        self.proc.wait()
        deadline = time.monotonic() + timeout_s
        while group_alive(self.pgid) and time.monotonic() < deadline:
            signal_group(self.pgid, signal.SIGKILL)
            time.sleep(0.01)  # grandchildren are reaped by init: nothing to wait on but the group
        if group_alive(self.pgid):
            log.warning("process group %d of %s still has members after SIGKILL", self.pgid, self.name)
        else:
            REGISTRY.remove(self.pgid)
        if not self._fh.closed:
            self._fh.close()

    def tail(self, n: int = 12) -> str:
        try:
            lines = self.log_path.read_text(errors="replace").splitlines()[-n:]
        except OSError:
            lines = []
        return f"--- {self.log_path.name} (pid {self.pid}, exit {self.proc.returncode})\n" + "\n".join(lines)

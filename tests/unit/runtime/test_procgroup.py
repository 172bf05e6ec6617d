"""tagswarm.runtime.procgroup: a child leads its own process group, stopping it takes its
grandchildren too (also when frozen), and the reaper kills the groups it was told about once
the test process's end of the pipe closes.  Plain ``sleep`` processes: no network."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import psutil

from tagswarm.runtime import reaper
from tagswarm.runtime.procgroup import REAPER, Child, group_alive

#: a shell that starts a grandchild in its own group and waits
FAMILY = ["/bin/sh", "-c", "sleep 300 & echo started; wait"]


def _until(cond: object, timeout_s: float = 10.0) -> bool:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if cond():  # type: ignore[operator]
            return True
        time.sleep(0.01)
    return bool(cond())  # type: ignore[operator]


def _members(pgid: int) -> list[psutil.Process]:
    out = []
    for p in psutil.process_iter():
        try:
            if os.getpgid(p.pid) == pgid and p.status() != psutil.STATUS_ZOMBIE:
                out.append(p)
        except (ProcessLookupError, psutil.Error):
            pass
    return out


def test_a_child_leads_its_own_group_and_stop_ends_all_of_it(tmp_path: Path) -> None:
    child = Child("family", FAMILY, tmp_path / "family.log", dict(os.environ))
    assert os.getpgid(child.pid) == child.pid != os.getpgid(0)
    assert _until(lambda: len(_members(child.pgid)) == 2)  # the shell and its sleep
    child.send(signal.SIGSTOP)  # frozen: SIGTERM alone would wait for a SIGCONT
    child.stop(grace_s=0.5)
    assert not group_alive(child.pgid) and _members(child.pgid) == []
    assert "started" in child.tail()


def test_the_reaper_kills_every_group_it_was_told_about_when_the_pipe_closes(tmp_path: Path) -> None:
    reaper = subprocess.Popen([sys.executable, str(REAPER)], stdin=subprocess.PIPE, start_new_session=True)
    kids = [subprocess.Popen(FAMILY, start_new_session=True, stdout=subprocess.DEVNULL) for _ in range(2)]
    spared = subprocess.Popen(["sleep", "300"], start_new_session=True)
    try:
        assert _until(lambda: all(len(_members(k.pid)) == 2 for k in kids))
        assert reaper.stdin is not None
        reaper.stdin.write(f"+{kids[0].pid}\n+{kids[1].pid}\n+{spared.pid}\n-{spared.pid}\n".encode())
        reaper.stdin.close()  # what the end of the test process does, however it ends
        assert reaper.wait(timeout=10) == 0
        assert all(k.wait(timeout=10) == -signal.SIGKILL for k in kids)
        assert _until(lambda: _members(kids[0].pid) == [] and _members(kids[1].pid) == [])
        assert spared.poll() is None  # told it was gone: left alone
    finally:
        for p in (*kids, spared):
            if p.poll() is None:
                os.killpg(p.pid, signal.SIGKILL)
                p.wait()


def test_the_reaper_keeps_the_groups_still_listed() -> None:
    assert reaper.follow(["+10\n", "+11\n", "-10\n", "junk\n", "+\n", "-99\n", "+12"]) == {11, 12}

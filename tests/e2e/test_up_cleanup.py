"""``tagswarm up`` killed outright (SIGKILL, as a test runner's timeout or the OOM killer
does) leaves no world, server, agent or render worker behind: the reaper takes them down."""

from __future__ import annotations

import os
import signal
import subprocess
import time
from pathlib import Path

import psutil

from tests.harness import endpoint, script


def _descendants(pid: int) -> list[psutil.Process]:
    try:
        return psutil.Process(pid).children(recursive=True)
    except psutil.NoSuchProcess:
        return []


def test_sigkilled_up_leaves_no_process_behind(tmp_path: Path) -> None:
    log = open(tmp_path / "up.log", "wb")
    proc = subprocess.Popen([script("tagswarm"), "up", "--duration", "120", "--robots", "2", "--listen", endpoint(),
                             "--run", f"reap{os.getpid()}", "--out", str(tmp_path / "run"), "--no-live", "--no-report",
                             "--set", "render.workers=1"],
                            stdout=log, stderr=subprocess.STDOUT,
                            env={k: v for k, v in os.environ.items() if not k.startswith("TAGSWARM_")})
    kids: list[psutil.Process] = []
    try:
        # wait until the whole swarm runs: world, server, two agents and the world's render worker
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline and proc.poll() is None:
            kids = _descendants(proc.pid)
            names = " ".join(" ".join(k.cmdline()) for k in kids if k.is_running())
            # (the world starts its render workers as ``python -m tagswarm.world.render_worker``)
            if all(s in names for s in ("tagswarm-world", "tagswarm-server", "tagswarm-agent", "render_worker")):
                break
            time.sleep(0.2)
        assert proc.poll() is None, (tmp_path / "up.log").read_text()
        assert time.monotonic() < deadline, f"the swarm did not start: {names}"
        swarm = [k for k in kids if any(s in " ".join(k.cmdline())
                                        for s in ("tagswarm-", "tagswarm.view", "render_worker"))]
        assert len(swarm) >= 5, [k.cmdline() for k in kids]
        assert any("render_worker" in " ".join(k.cmdline()) for k in swarm)
        proc.send_signal(signal.SIGKILL)
        proc.wait(timeout=10)
        gone, alive = psutil.wait_procs(swarm, timeout=15)
        assert not alive, [(p.pid, p.cmdline()) for p in alive]
        assert len(gone) == len(swarm)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
        for k in kids:
            try:
                k.kill()
            except psutil.NoSuchProcess:
                pass
        log.close()

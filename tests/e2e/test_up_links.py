"""``tagswarm up`` survives its links being cut mid-run: it is the run's Zenoh router, every
child its client, and a client re-opens its link by itself.  (In the peer mesh ``up`` ran before,
a link Zenoh's gossip had made was never re-made: the recorder stopped hearing the server
for the rest of the run.)  The cut is real: ``ss -K`` destroys the TCP sockets of ``up``'s
own process, as a lease expiry on a saturated machine closes them."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import time
from pathlib import Path

import numpy as np
import psutil
import pytest

from tests.harness import endpoint, script

DURATION_S = 20.0
ROBOTS = 3


def _links(pid: int) -> list[tuple[int, int]]:
    """(local port, remote port) of every established TCP socket of process ``pid``."""
    return [(c.laddr.port, c.raddr.port) for c in psutil.Process(pid).net_connections(kind="tcp")
            if c.status == psutil.CONN_ESTABLISHED and c.raddr]


def test_up_remakes_the_links_of_its_own_process_cut_mid_run(tmp_path: Path) -> None:
    if shutil.which("ss") is None:
        pytest.skip("needs ss (iproute2) to cut sockets")
    out = tmp_path / "run"
    log = tmp_path / "up.log"
    proc = subprocess.Popen([script("tagswarm"), "up", "--clock", "realtime", "--duration", str(DURATION_S),
                             "--robots", str(ROBOTS), "--seed", "0", "--listen", endpoint(), "--run",
                             f"links{os.getpid()}", "--out", str(out), "--no-live"],
                            stdout=open(log, "wb"), stderr=subprocess.STDOUT,
                            env={k: v for k, v in os.environ.items() if not k.startswith("TAGSWARM_")})
    try:
        # --no-live prints "t=<sim> s" every 5 s of wall time once the run is under way
        deadline = time.monotonic() + 120
        while time.monotonic() < deadline and proc.poll() is None and "t=" not in log.read_text(errors="replace"):
            time.sleep(0.2)
        assert proc.poll() is None and time.monotonic() < deadline, log.read_text(errors="replace")
        cut = _links(proc.pid)
        assert cut, "up has no TCP link to cut"
        for local, remote in cut:
            subprocess.run(["ss", "-K", "sport", "=", f":{local}", "dport", "=", f":{remote}"],
                           capture_output=True, check=False)
        still = set(_links(proc.pid)) & set(cut)
        if still:
            pytest.skip(f"this kernel cannot destroy sockets (ss -K, CONFIG_INET_DIAG_DESTROY): {sorted(still)}")
        assert proc.wait(timeout=180) == 0, log.read_text(errors="replace")
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    metrics = json.loads((out / "metrics.json").read_text())
    assert not [w for w in metrics.get("warnings", []) if "heard nothing" in w], metrics["warnings"]
    # what the recorder heard after the cut: every robot's fused pose (from the server) and
    # odometry (from its agent) until the end of the run
    for rid in range(ROBOTS):
        for kind in ("fused", "odom"):
            t_end = np.loadtxt(out / "trajectories" / f"{kind}_{rid}.tum", ndmin=2)[-1, 0]
            assert t_end >= DURATION_S - 1.0, (kind, rid, t_end)
    assert metrics["swarm"]["fused"]["time_localised_placed"] > 0.9

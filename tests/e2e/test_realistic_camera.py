"""The paper scenario through the realistic camera (``paper-realistic``: wide-lens
distortion, noise, motion blur, vignetting; docs/camera.md), end to end with
``tagswarm up`` in lockstep: every robot ends within 10 cm of the truth and its fused
trajectory stays within 10 cm RMSE.  Full-length accuracy: bench/accuracy.py."""

from __future__ import annotations

import json
import subprocess
from pathlib import Path

import numpy as np

from tests.harness import script

DURATION_S = 30.0


def _final_error(run: Path, rid: int) -> float:
    truth = np.loadtxt(run / "trajectories" / f"truth_{rid}.tum", ndmin=2)
    fused = np.loadtxt(run / "trajectories" / f"fused_{rid}.tum", ndmin=2)
    i = int(np.argmin(np.abs(fused[:, 0] - truth[-1, 0])))
    assert abs(fused[i, 0] - truth[-1, 0]) < 0.1
    return float(np.hypot(fused[i, 1] - truth[-1, 1], fused[i, 2] - truth[-1, 2]))


def test_paper_realistic_localises_every_robot(tmp_path: Path) -> None:
    out = tmp_path / "run"
    res = subprocess.run([script("tagswarm"), "up", "--scenario", "paper-realistic", "--clock", "lockstep",
                          "--seed", "0", "--duration", str(DURATION_S), "--out", str(out), "--no-live"],
                         capture_output=True, text=True, timeout=1200)
    assert res.returncode == 0, res.stdout[-3000:] + res.stderr[-3000:]
    scenario = json.loads((out / "scenario.json").read_text())
    assert scenario["camera"]["preset"] == "realistic"
    m = json.loads((out / "metrics.json").read_text())
    for rid, r in m["robots"].items():
        assert r["fused"]["ate_unaligned"]["rmse"] <= 0.10, (rid, r["fused"]["ate_unaligned"])
        assert _final_error(out, int(rid)) <= 0.10, rid

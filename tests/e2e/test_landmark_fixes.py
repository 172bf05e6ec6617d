"""The marker document's self-localisation end to end (issue 20), landmarks scenario,
lockstep: with several field tags in view an agent solves its pose from all of them
jointly (agents/landmarkfix.py) and sends one absolute observation naming every tag it
used; the server counts those (``multi_landmark_fixes``) and fuses them (its fusion's
``accepted_landmarks``), and every robot ends within 10 cm of the truth in the arena
frame (with landmarks the map frame is the arena frame)."""

from __future__ import annotations

import json
import subprocess
from pathlib import Path

from tests.harness import script

DURATION_S = 30.0


def test_landmarks_joint_fixes_are_fused_and_every_robot_ends_within_10cm(tmp_path: Path) -> None:
    out = tmp_path / "run"
    res = subprocess.run([script("tagswarm"), "up", "--scenario", "landmarks", "--clock", "lockstep", "--seed", "0",
                          "--duration", str(DURATION_S), "--out", str(out), "--no-live"],
                         capture_output=True, text=True, timeout=900)
    assert res.returncode == 0, res.stdout[-3000:] + res.stderr[-3000:]
    server = json.loads((out / "run.json").read_text())["counters"]["server"]
    assert server.get("multi_landmark_fixes", 0) > 0, server
    assert server.get("fusion_accepted_landmarks", 0) > 0, server
    m = json.loads((out / "metrics.json").read_text())
    for rid in m["robots"]:
        truth = (out / "trajectories" / f"truth_{rid}.tum").read_text().splitlines()[-1].split()
        fused = (out / "trajectories" / f"fused_{rid}.tum").read_text().splitlines()[-1].split()
        assert abs(float(fused[0]) - float(truth[0])) < 0.1, rid
        err = ((float(fused[1]) - float(truth[1])) ** 2 + (float(fused[2]) - float(truth[2])) ** 2) ** 0.5
        assert err <= 0.10, (rid, err)

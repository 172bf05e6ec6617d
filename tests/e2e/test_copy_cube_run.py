"""Copy cubes end to end (``[[decoys]] kind = "cube"``; docs/camera.md, Decoys): the paper
scenario, lockstep, with two static copies of robots (robot 2's cube behind the origin
robot, robot 1's in the far corner, both in view of the origin robot or the patrols).  The
agents count them (two plausible robots of one identity in one image: ``duplicate``), the
server gates the copies seen alone, nothing is re-localised onto a copy, and the fused
trajectories stay within 1 cm of a run without them.

Expected to fail until two changes outside this test's files land (docs/camera.md, Decoys):
world/render.py must build decoys through world/decoys.py (today it draws every decoy as a
poster), and the server's re-localisation must not accept a single witness's repeated
sightings of a copy that stays put while the copied robot's odometry moves (measured: six
re-localisations onto the copies, robots 1 and 2 moved 3.0 and 3.8 m)."""

from __future__ import annotations

import json
import subprocess
from pathlib import Path

import numpy as np
import pytest

from tests.harness import script

COPIES = ('decoys=[{kind="cube", tag_id=21, x_m=-2.8, y_m=-1.2, yaw_rad=0.0}, '
          '{kind="cube", tag_id=11, x_m=2.6, y_m=2.0, yaw_rad=3.1416}]')
RUN_S = 20.0


def _up(out: Path, *extra: str) -> dict[str, dict[str, int]]:
    res = subprocess.run([script("tagswarm"), "up", "--scenario", "paper", "--clock", "lockstep", "--seed", "0",
                          "--duration", str(RUN_S), "--out", str(out), "--no-live", "--no-report", *extra],
                         capture_output=True, text=True, timeout=1200)
    assert res.returncode == 0, res.stdout[-3000:] + res.stderr[-3000:]
    counters: dict[str, dict[str, int]] = json.loads((out / "run.json").read_text())["counters"]
    return counters


def _agents(counters: dict[str, dict[str, int]], name: str) -> int:
    return sum(c.get(name, 0) for who, c in counters.items() if who.startswith("agent/"))


# not run until then (two 20 s runs, ~100 s of CI, to fail for a known reason); drop the mark with the changes
@pytest.mark.xfail(run=False, reason="needs world/render.py to build copy cubes (world/decoys.py) and the "
                                     "server's re-localisation to reject a static copy (see the module docstring)")
def test_copy_cubes_are_counted_and_never_move_the_map(tmp_path: Path) -> None:
    plain = _up(tmp_path / "plain")
    copied = _up(tmp_path / "copies", "--set", COPIES)
    assert _agents(copied, "pose_rejected_duplicate") > _agents(plain, "pose_rejected_duplicate")
    assert copied["server"].get("fusion_rejected_gate", 0) > plain["server"].get("fusion_rejected_gate", 0)
    assert copied["server"].get("fusion_relocalisations", 0) == plain["server"].get("fusion_relocalisations", 0)
    for rid in range(4):
        a = np.loadtxt(tmp_path / "plain" / "trajectories" / f"fused_{rid}.tum", ndmin=2)
        b = np.loadtxt(tmp_path / "copies" / "trajectories" / f"fused_{rid}.tum", ndmin=2)
        common, ia, ib = np.intersect1d(a[:, 0], b[:, 0], return_indices=True)
        assert len(common) > 0.9 * min(len(a), len(b)), rid
        gap = np.hypot(a[ia, 1] - b[ib, 1], a[ia, 2] - b[ib, 2])
        assert float(gap.max()) <= 0.01, (rid, float(gap.max()))

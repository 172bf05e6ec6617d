"""Copy cubes end to end (``[[decoys]] kind = "cube"``; docs/camera.md, Decoys): the paper
scenario, lockstep, with two static copies of robots (robot 2's cube behind the origin
robot, robot 1's in the far corner, both in view of the origin robot or the patrols).  The
agents count them (two plausible robots of one identity in one image: ``duplicate``; a
sighting far from where the map has that robot: ``sightings_off_map``, no local fix), the
server gates the copies seen alone and remembers their places as decoy sites (a robot
cannot be in two places), nothing is re-localised onto a copy, and every robot's fused
error stays what it is without them.  Once the map has a robot, an agent that sees it
beside its copy tells them apart by where the map has it (``duplicates_resolved_by_map``)
and drops its later sightings of the copy alone there (``sightings_at_copy_site``).
Before that nobody can tell them apart and neither is trusted, so a patrol is placed a
tick later and its turns, which follow its fixes, differ: the patrols' trajectories
differ.  With the motion taken out (every robot holding station), the fused trajectories
with copies are those without, within 1 cm, once the map has every robot (after 1 s)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from tests.harness import agents_total, paper_counters

COPIES = ('decoys=[{kind="cube", tag_id=21, x_m=-2.8, y_m=-1.2, yaw_rad=0.0}, '
          '{kind="cube", tag_id=11, x_m=2.6, y_m=2.0, yaw_rad=3.1416}]')
RUN_S = 20.0
HOLD_S = 12.0


def _fused_errors(run: Path, rid: int) -> np.ndarray:
    """Fused position error (m) at every fused sample, against the truth sample nearest in time."""
    truth = np.loadtxt(run / "trajectories" / f"truth_{rid}.tum", ndmin=2)
    fused = np.loadtxt(run / "trajectories" / f"fused_{rid}.tum", ndmin=2)
    i = np.clip(np.searchsorted(truth[:, 0], fused[:, 0]), 0, len(truth) - 1)
    return np.asarray(np.hypot(fused[:, 1] - truth[i, 1], fused[:, 2] - truth[i, 2]))


def test_copy_cubes_are_counted_and_never_move_the_map(tmp_path: Path) -> None:
    plain = paper_counters(tmp_path / "plain", RUN_S, "--no-report")
    copied = paper_counters(tmp_path / "copies", RUN_S, "--no-report", "--set", COPIES)
    assert agents_total(copied, "pose_rejected_duplicate") > agents_total(plain, "pose_rejected_duplicate")
    server = copied["server"]
    assert server.get("fusion_rejected_gate", 0) > plain["server"].get("fusion_rejected_gate", 0)
    assert server.get("fusion_reloc_decoy_site", 0) > 0  # the copies' places were recognised
    assert server.get("fusion_relocalisations", 0) == plain["server"].get("fusion_relocalisations", 0) == 0
    assert agents_total(copied, "sightings_off_map") > agents_total(plain, "sightings_off_map")
    for rid in range(4):
        clean, dirty = _fused_errors(tmp_path / "plain", rid), _fused_errors(tmp_path / "copies", rid)
        assert float(np.sqrt(np.mean(dirty**2))) <= float(np.sqrt(np.mean(clean**2))) + 0.01, rid
        assert float(dirty[-1]) <= 0.03, (rid, float(dirty[-1]))


def _gap_m(a_run: Path, b_run: Path, rid: int, after_s: float) -> float:
    """Largest distance (m) between two runs' fused positions of ``rid`` at their common stamps
    after ``after_s``."""
    a = np.loadtxt(a_run / "trajectories" / f"fused_{rid}.tum", ndmin=2)
    b = np.loadtxt(b_run / "trajectories" / f"fused_{rid}.tum", ndmin=2)
    common, ia, ib = np.intersect1d(a[:, 0], b[:, 0], return_indices=True)
    assert len(common) > 0.9 * min(len(a), len(b)), rid
    late = common > after_s
    return float(np.hypot(a[ia, 1] - b[ib, 1], a[ia, 2] - b[ib, 2])[late].max())


def test_copy_cubes_leave_the_fused_trajectories_of_a_holding_swarm_as_they_are(tmp_path: Path) -> None:
    hold = ("--no-report", "--set", "missions=[]")
    paper_counters(tmp_path / "plain", HOLD_S, *hold)
    copied = paper_counters(tmp_path / "copies", HOLD_S, *hold, "--set", COPIES)
    assert agents_total(copied, "duplicates_resolved_by_map") > 0  # the origin robot sees robot 1 beside its copy
    assert copied["server"].get("fusion_relocalisations", 0) == 0
    for rid in range(1, 4):
        assert _gap_m(tmp_path / "plain", tmp_path / "copies", rid, after_s=1.0) <= 0.01, rid

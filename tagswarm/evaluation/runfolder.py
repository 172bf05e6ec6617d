"""Reading a run folder (the contract ``tagswarm up`` writes) for :mod:`tagswarm.evaluation.metrics`.

Pure code: files in, arrays and trajectories out; a missing or malformed folder
raises :class:`RunFolderError` with a one-line message naming the file.

- ``run.json``: a JSON object with at least ``robots`` (list of ids); the rest
  (``clock``, ``counters``, ``scenario`` ...) is kept as ``RunData.info``.
- ``trajectories/{truth,odom,fused}_<k>.tum``: evo reads them (TUM, seconds and
  metres, MAP frame).  A missing or empty file is ``None``: legal for ``fused``
  (robot k was never localised), a warning for ``truth`` and ``odom``.
- ``observations.csv`` (:data:`OBS_HEADER`) and ``modes.csv`` (:data:`MODES_HEADER`):
  ``stamp_ns`` columns become simulation seconds; a missing file is a warning.
- ``trajectories/fused_cov_<k>.csv``, ``relocalisations.csv`` and
  ``world_commands.csv`` (formats in :mod:`tagswarm.evaluation.runformat`): newer than the
  rest of the contract, so a missing file is silently empty (``None`` for a
  covariance file: NEES is then ``null``).
"""

from __future__ import annotations

import csv
import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from evo import EvoException
from evo.core.trajectory import PoseTrajectory3D
from evo.tools import file_interface
from numpy.typing import NDArray

from tagswarm.evaluation.runformat import (
    FUSED_COV_HEADER,
    INTERVENTIONS_HEADER,
    OBS_COV_COLUMNS,
    OBS_HEADER,
    RELOC_HEADER,
    WORLD_COMMANDS_HEADER,
)
from tagswarm.protocol.errors import UsageError

F64 = NDArray[np.float64]

MODES_HEADER = ("stamp_ns", "robot", "mode")


class RunFolderError(UsageError, ValueError):
    """The run folder is missing or malformed; the message is one line naming the file."""


@dataclass(frozen=True)
class Observations:
    """Relative observations published by the agents (one row each of ``observations.csv``).
    ``stamp_s`` simulation seconds; ``target_id`` is a robot id when ``is_robot``,
    else a landmark tag id; ``rel`` (N, 3) what the observer measured: the target's base
    (a landmark's tag frame) in its own base frame, (x_m, y_m, yaw_rad); ``cov`` (N, 3, 3)
    the covariance the observer sent with it (same axes; NaN where the run folder has none)."""

    stamp_s: F64
    observer: NDArray[np.int64]
    is_robot: NDArray[np.bool_]
    target_id: NDArray[np.int64]
    rel: F64
    cov: F64 | None = None

    def covariances(self) -> F64:
        """(N, 3, 3) :attr:`cov`, all NaN when the run folder predates it."""
        if self.cov is None:
            return np.full((self.stamp_s.size, 3, 3), np.nan)
        return self.cov

    @staticmethod
    def empty() -> Observations:
        return Observations(np.zeros(0), np.zeros(0, np.int64), np.zeros(0, bool), np.zeros(0, np.int64),
                            np.zeros((0, 3)), np.zeros((0, 3, 3)))


@dataclass(frozen=True)
class ModeSample:
    """One row of ``modes.csv``: robot ``robot`` was in ``mode`` at ``stamp_s`` (sim seconds)."""

    stamp_s: float
    robot: int
    mode: str


@dataclass(frozen=True)
class RelocEvent:
    """One row of ``relocalisations.csv``: the server re-initialised ``robot`` at
    ``stamp_s`` (sim seconds), moving its estimate by ``jump_m`` from ``from_pose`` to
    ``to_pose`` (map frame, (x_m, y_m, yaw_rad)) on ``evidence`` observations by
    ``observers`` (robot ids, -1 = a landmark)."""

    stamp_s: float
    robot: int
    jump_m: float
    from_pose: tuple[float, float, float]
    to_pose: tuple[float, float, float]
    evidence: int
    observers: tuple[int, ...]


@dataclass(frozen=True)
class WorldCommandRow:
    """One row of ``world_commands.csv`` (a kidnap): ``action`` ("teleport"/"push") of
    ``robot`` with (x_m, y_m, yaw_rad) in the ARENA frame, stamped ``stamp_s`` by its
    sender and received at ``received_s`` (sim seconds)."""

    stamp_s: float
    robot: int
    action: str
    x_m: float
    y_m: float
    yaw_rad: float
    received_s: float


@dataclass(frozen=True)
class CovTrack:
    """``fused_cov_<k>.csv``: ``stamp_s`` (N,) sim seconds and ``cov`` (N, 3, 3) of (x, y, yaw)
    in the robot's own axes (see :mod:`tagswarm.evaluation.covframe`)."""

    stamp_s: F64
    cov: F64


@dataclass
class RunData:
    """A loaded run folder.  Trajectories are in the map frame; ``None`` means the file
    is missing or holds no pose."""

    path: Path
    info: dict[str, Any]
    robots: tuple[int, ...]
    truth: dict[int, PoseTrajectory3D | None]
    odom: dict[int, PoseTrajectory3D | None]
    fused: dict[int, PoseTrajectory3D | None]
    observations: Observations
    modes: list[ModeSample]
    warnings: list[str] = field(default_factory=list)
    fused_cov: dict[int, CovTrack | None] = field(default_factory=dict)
    relocalisations: list[RelocEvent] = field(default_factory=list)
    world_commands: list[WorldCommandRow] = field(default_factory=list)
    #: the interventions the world applied (``interventions.csv``); None for a run folder older than it
    applied: list[WorldCommandRow] | None = None

    def estimate(self, kind: str, robot: int) -> PoseTrajectory3D | None:
        """The ``kind`` ("fused"/"odom") trajectory of ``robot``."""
        table = self.fused if kind == "fused" else self.odom
        return table.get(robot)


def read_tum(path: Path) -> PoseTrajectory3D | None:
    """A TUM trajectory (``t x y z qx qy qz qw``, seconds/metres) read by evo, or
    ``None`` if the file is missing or has no pose line.  Raises
    :class:`RunFolderError` on a malformed file."""
    if not path.is_file():
        return None
    try:
        text = path.read_text()
    except OSError as exc:
        raise RunFolderError(f"cannot read {path}: {exc.strerror}") from None
    # evo refuses empty files; an empty fused file is a legal "never localised"
    if not any(line.strip() and not line.lstrip().startswith("#") for line in text.splitlines()):
        return None
    try:
        traj = file_interface.read_tum_trajectory_file(str(path))
    except (EvoException, ValueError) as exc:
        raise RunFolderError(f"{path}: not a TUM trajectory ({exc})") from None
    if not np.all(np.isfinite(traj.positions_xyz)) or not np.all(np.isfinite(traj.timestamps)):
        raise RunFolderError(f"{path}: non-finite value in a pose")
    if np.any(np.diff(traj.timestamps) < 0):
        # evo's association assumes sorted stamps; sorting keeps a hand-made file usable
        order = np.argsort(traj.timestamps, kind="stable")
        traj.reduce_to_ids(order)
    return traj


def _read_csv(path: Path, header: tuple[str, ...], warnings: list[str]) -> list[dict[str, str]]:
    if not path.is_file():
        warnings.append(f"{path.name} is missing")
        return []
    try:
        with path.open(newline="") as f:
            reader = csv.DictReader(f)
            fields = tuple(reader.fieldnames or ())
            if fields[: len(header)] != header:
                raise RunFolderError(f"{path}: header must start with {','.join(header)}, got {','.join(fields)}")
            return list(reader)
    except OSError as exc:
        raise RunFolderError(f"cannot read {path}: {exc.strerror}") from None


def _int(value: str, path: Path, line: int, name: str) -> int:
    try:
        return int(value)
    except (TypeError, ValueError):
        raise RunFolderError(f"{path}:{line}: {name} must be an integer, got {value!r}") from None


def read_observations(path: Path, warnings: list[str]) -> Observations:
    """``observations.csv`` (header :data:`OBS_HEADER`)."""
    rows = _read_csv(path, OBS_HEADER, warnings)
    if not rows:
        return Observations.empty()
    stamps, observers, robot, target, rel, cov = [], [], [], [], [], []
    upper = ((0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2))
    for i, r in enumerate(rows, start=2):
        stamps.append(_int(r["stamp_ns"], path, i, "stamp_ns") / 1e9)
        observers.append(_int(r["observer"], path, i, "observer"))
        kind = (r["target_kind"] or "").strip()
        if kind not in ("robot", "landmark"):
            raise RunFolderError(f"{path}:{i}: target_kind must be robot or landmark, got {kind!r}")
        robot.append(kind == "robot")
        target.append(_int(r["target_id"], path, i, "target_id"))
        # a non-finite measurement is kept (as NaN) and skipped by the metrics that read it: who saw whom stands
        rel.append(tuple(_float(r[k], path, i, k, finite=False) for k in ("x_m", "y_m", "yaw_rad")))
        c = np.full((3, 3), np.nan)
        for (a, b), k in zip(upper, OBS_COV_COLUMNS, strict=True):
            if r.get(k) not in (None, ""):  # older run folders have no covariance columns
                c[a, b] = c[b, a] = _float(r[k], path, i, k, finite=False)
        cov.append(c)
    return Observations(np.array(stamps, float), np.array(observers, np.int64), np.array(robot, bool),
                        np.array(target, np.int64), np.array(rel, float).reshape(-1, 3),
                        np.array(cov, float).reshape(-1, 3, 3))


def read_modes(path: Path, warnings: list[str]) -> list[ModeSample]:
    """``modes.csv`` (header :data:`MODES_HEADER`), sorted by time."""
    out = []
    for i, r in enumerate(_read_csv(path, MODES_HEADER, warnings), start=2):
        out.append(ModeSample(_int(r["stamp_ns"], path, i, "stamp_ns") / 1e9, _int(r["robot"], path, i, "robot"),
                              (r["mode"] or "").strip()))
    return sorted(out, key=lambda s: (s.robot, s.stamp_s))


def _float(value: str, path: Path, line: int, name: str, finite: bool = True) -> float:
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise RunFolderError(f"{path}:{line}: {name} must be a number, got {value!r}") from None
    if not math.isfinite(v):
        if not finite:
            return math.nan
        raise RunFolderError(f"{path}:{line}: {name} must be finite, got {value!r}")
    return v


def _optional_rows(path: Path, header: tuple[str, ...]) -> list[dict[str, str]]:
    """Rows of a CSV file that older run folders lack: a missing file is no rows, silently."""
    return _read_csv(path, header, []) if path.is_file() else []


def read_relocalisations(path: Path) -> list[RelocEvent]:
    """``relocalisations.csv`` (header :data:`~tagswarm.evaluation.runformat.RELOC_HEADER`), sorted by time."""
    out = []
    for i, r in enumerate(_optional_rows(path, RELOC_HEADER), start=2):
        f = {n: _float(r[n], path, i, n) for n in RELOC_HEADER[2:9]}
        observers = tuple(_int(o, path, i, "observers") for o in (r["observers"] or "").split())
        out.append(RelocEvent(_int(r["stamp_ns"], path, i, "stamp_ns") / 1e9, _int(r["robot_id"], path, i, "robot_id"),
                              f["jump_m"], (f["from_x_m"], f["from_y_m"], f["from_yaw_rad"]),
                              (f["to_x_m"], f["to_y_m"], f["to_yaw_rad"]), _int(r["evidence"], path, i, "evidence"),
                              observers))
    return sorted(out, key=lambda e: (e.stamp_s, e.robot))


def read_world_commands(path: Path) -> list[WorldCommandRow]:
    """``world_commands.csv`` (header :data:`~tagswarm.evaluation.runformat.WORLD_COMMANDS_HEADER`), sorted by time."""
    out = []
    for i, r in enumerate(_optional_rows(path, WORLD_COMMANDS_HEADER), start=2):
        action = (r["action"] or "").strip()
        if action not in ("teleport", "push"):
            raise RunFolderError(f"{path}:{i}: action must be teleport or push, got {action!r}")
        out.append(WorldCommandRow(_int(r["stamp_ns"], path, i, "stamp_ns") / 1e9,
                                   _int(r["robot_id"], path, i, "robot_id"), action,
                                   _float(r["x_m"], path, i, "x_m"), _float(r["y_m"], path, i, "y_m"),
                                   _float(r["yaw_rad"], path, i, "yaw_rad"),
                                   _int(r["received_ns"], path, i, "received_ns") / 1e9))
    return sorted(out, key=lambda c: (c.stamp_s, c.robot))


def read_interventions(path: Path) -> list[WorldCommandRow] | None:
    """``interventions.csv`` (header :data:`~tagswarm.evaluation.runformat.INTERVENTIONS_HEADER`), sorted by
    time, as rows received when applied; None if the run folder has no such file (older than it)."""
    if not path.is_file():
        return None
    out = []
    for i, r in enumerate(_read_csv(path, INTERVENTIONS_HEADER, []), start=2):
        action = (r["action"] or "").strip()
        if action not in ("teleport", "push"):
            raise RunFolderError(f"{path}:{i}: action must be teleport or push, got {action!r}")
        t = _int(r["stamp_ns"], path, i, "stamp_ns") / 1e9
        out.append(WorldCommandRow(t, _int(r["robot_id"], path, i, "robot_id"), action,
                                   _float(r["x_m"], path, i, "x_m"), _float(r["y_m"], path, i, "y_m"),
                                   _float(r["yaw_rad"], path, i, "yaw_rad"), t))
    return sorted(out, key=lambda c: (c.stamp_s, c.robot))


def read_fused_cov(path: Path) -> CovTrack | None:
    """``fused_cov_<k>.csv`` (header :data:`~tagswarm.evaluation.runformat.FUSED_COV_HEADER`), sorted by
    time, or ``None`` if the file is missing or has no row."""
    rows = _optional_rows(path, FUSED_COV_HEADER)
    if not rows:
        return None
    stamps = np.array([_int(r["stamp_ns"], path, i, "stamp_ns") / 1e9 for i, r in enumerate(rows, start=2)])
    cov = np.array([[_float(r[n], path, i, n) for n in FUSED_COV_HEADER[1:]] for i, r in enumerate(rows, start=2)])
    order = np.argsort(stamps, kind="stable")
    return CovTrack(stamps[order], cov[order].reshape(-1, 3, 3))


def load_run(run_dir: Path) -> RunData:
    """Read a run folder.  Raises :class:`RunFolderError` if it is not a directory, has
    no readable ``run.json`` with a ``robots`` list, or holds a malformed file.  Missing
    optional inputs (a robot's trajectories, the CSV files) become warnings."""
    run_dir = Path(run_dir)
    if not run_dir.is_dir():
        raise RunFolderError(f"{run_dir} is not a run folder (no such directory)")
    info_path = run_dir / "run.json"
    if not info_path.is_file():
        raise RunFolderError(f"{run_dir} is not a run folder (no run.json)")
    try:
        info = json.loads(info_path.read_text())
    except (OSError, ValueError) as exc:
        raise RunFolderError(f"{info_path}: cannot be parsed ({exc})") from None
    if not isinstance(info, dict):
        raise RunFolderError(f"{info_path}: must hold a JSON object")
    robots = info.get("robots")
    if not isinstance(robots, list) or not all(isinstance(r, int) and not isinstance(r, bool) for r in robots):
        raise RunFolderError(f"{info_path}: 'robots' must be a list of robot ids")
    warnings: list[str] = []
    traj_dir = run_dir / "trajectories"
    tables: dict[str, dict[int, PoseTrajectory3D | None]] = {"truth": {}, "odom": {}, "fused": {}}
    for k in robots:
        for kind, table in tables.items():
            table[k] = read_tum(traj_dir / f"{kind}_{k}.tum")
            if table[k] is None and kind != "fused":
                warnings.append(f"robot {k}: no {kind} trajectory")
    return RunData(
        path=run_dir, info=info, robots=tuple(robots), truth=tables["truth"], odom=tables["odom"],
        fused=tables["fused"], observations=read_observations(run_dir / "observations.csv", warnings),
        modes=read_modes(run_dir / "modes.csv", warnings), warnings=warnings,
        fused_cov={k: read_fused_cov(traj_dir / f"fused_cov_{k}.csv") for k in robots},
        relocalisations=read_relocalisations(run_dir / "relocalisations.csv"),
        world_commands=read_world_commands(run_dir / "world_commands.csv"),
        applied=read_interventions(run_dir / "interventions.csv"),
    )

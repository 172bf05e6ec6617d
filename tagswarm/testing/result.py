"""A finished run: its folder, ``metrics.json`` and trajectories."""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path
from typing import Any

from tagswarm.protocol.scenario import Scenario
from tagswarm.testing.errors import SwarmError
from tagswarm.testing.trajectories import KINDS, Array, planar, position_errors, read_tum


@dataclass
class Run:
    """What a finished swarm left: ``run_dir`` (the run folder ``tagswarm up`` writes:
    ``run.json``, ``metrics.json``, ``trajectories/``, ``logs/``, CSVs), ``metrics`` (the
    ``metrics.json`` dict, fields in :mod:`tagswarm.evaluation.metrics`), ``run_id`` (its
    Zenoh key namespace), the resolved ``scenario`` and each process's exit code.

    Trajectory arrays have rows ``(t_s, x_m, y_m, yaw_rad)`` in the map frame
    (:mod:`tagswarm.testing.trajectories`)."""

    run_id: str
    run_dir: Path
    scenario: Scenario
    metrics: dict[str, Any]
    exit_codes: dict[str, int | None] = field(default_factory=dict)

    @classmethod
    def load(cls, run_dir: Path, scenario: Scenario, run_id: str,
             exit_codes: dict[str, int | None] | None = None) -> Run:
        path = Path(run_dir) / "metrics.json"
        try:
            metrics = json.loads(path.read_text())
        except (OSError, ValueError) as exc:
            raise SwarmError(f"no readable metrics in {path}: {exc}") from None
        return cls(run_id=run_id, run_dir=Path(run_dir), scenario=scenario, metrics=metrics,
                   exit_codes=dict(exit_codes or {}))

    @property
    def robots(self) -> tuple[int, ...]:
        return tuple(self.scenario.robot_ids)

    @cached_property
    def _tracks(self) -> dict[tuple[str, int], Array]:
        return {}

    def trajectory(self, kind: str, robot: int) -> Array:
        """Robot ``robot``'s ``kind`` trajectory: ``truth`` (ground truth), ``fused`` (the server's
        corrected pose, only while localised) or ``odom`` (dead reckoning from the true start)."""
        if kind not in KINDS:
            raise SwarmError(f"trajectory kind must be one of {KINDS}, got {kind!r}")
        if robot not in self.robots:
            raise SwarmError(f"robot {robot} is not in this run (robots {list(self.robots)})")
        key = (kind, robot)
        if key not in self._tracks:
            self._tracks[key] = planar(read_tum(self.run_dir / "trajectories" / f"{kind}_{robot}.tum"))
        return self._tracks[key]

    def truth(self, robot: int) -> Array:
        return self.trajectory("truth", robot)

    def fused(self, robot: int) -> Array:
        return self.trajectory("fused", robot)

    def odom(self, robot: int) -> Array:
        return self.trajectory("odom", robot)

    def errors(self, robot: int, kind: str = "fused") -> Array:
        """(N, 2) rows ``t_s, error_m``: position error of each ``kind`` estimate against the truth at its time."""
        return position_errors(self.truth(robot), self.trajectory(kind, robot))

    def final_error(self, robot: int, kind: str = "fused") -> float:
        """Position error (m) of the robot's last ``kind`` estimate; inf if it has none."""
        e = self.errors(robot, kind)
        return float(e[-1, 1]) if len(e) else float("inf")

    def log(self, name: str) -> str:
        """The log of process ``name`` (``world``, ``server``, ``agent/<id>``; a restart's is ``agent/<id>.1``;
        ``world/0`` and ``server/0``, as the world's log names them, are the same).  A name with no log in
        the run folder is a :class:`SwarmError` naming those there are."""
        stem = _process(name).replace("/", "")
        path = self.run_dir / "logs" / f"{stem}.log"
        if not path.is_file():
            have = sorted(p.stem for p in (self.run_dir / "logs").glob("*.log"))
            raise SwarmError(f"no log of {name!r} in {self.run_dir / 'logs'} (there are: {', '.join(have) or 'none'})")
        return path.read_text(errors="replace")

    @cached_property
    def _counters(self) -> dict[str, dict[str, Any]]:
        try:
            table = json.loads((self.run_dir / "run.json").read_text()).get("counters", {})
        except (OSError, ValueError, AttributeError) as exc:
            raise SwarmError(f"no readable counters in {self.run_dir / 'run.json'}: {exc}") from None
        return table if isinstance(table, dict) else {}

    def counters(self, name: str) -> dict[str, Any]:
        """The last status counters of process ``name`` (``world``, ``server``, ``agent/<id>``), as in
        ``run.json``: e.g. ``controller_errors`` and ``controller_slow`` of a robot running your
        controller, ``contacts_robot_robot`` of the world.  :class:`SwarmError` for a name with none."""
        key = _process(name)
        if key not in self._counters:
            raise SwarmError(f"no counters of {name!r} in this run (there are: {', '.join(sorted(self._counters))})")
        return dict(self._counters[key])


def _process(name: str) -> str:
    """``world/0`` and ``server/0`` (participant names) are the processes ``world`` and ``server``."""
    return name.removesuffix("/0") if name in ("world/0", "server/0") else name

"""Records a running system from the outside (a read-only Zenoh client) and
writes the run folder that ``tagswarm report`` evaluates.

Everything is stored in the MAP frame (the origin robot's first pose, or the
arena frame when landmarks are used): ``truth`` is converted with the scenario's
``arena_to_map``; ``odom`` is each agent's dead reckoning started from the
robot's true initial pose (pure drift); ``fused`` is the server's corrected
pose, and ``fused_cov`` its covariance as published (row-major 3x3 of (x, y,
yaw), in the robot's own axes: see :mod:`tagswarm.evaluation.covframe`).  Relocalisation
events (map-frame poses) and world commands (kidnaps, arena frame) are stored as
received; file formats in :mod:`tagswarm.evaluation.runformat`.
"""

from __future__ import annotations

import csv
import json
import math
from collections import defaultdict
from pathlib import Path
from typing import Any

import msgspec

from tagswarm.evaluation.runformat import (
    FUSED_COV_HEADER,
    INTERVENTIONS_HEADER,
    OBS_COV_COLUMNS,
    OBS_HEADER,
    RELOC_HEADER,
    WORLD_COMMANDS_HEADER,
)
from tagswarm.protocol import codec
from tagswarm.protocol import messages as m
from tagswarm.protocol.bus import Bus
from tagswarm.protocol.geometry import Pose2, se2_compose
from tagswarm.protocol.keys import Keys
from tagswarm.protocol.layout import arena_to_map
from tagswarm.protocol.scenario import Scenario


def _tum_line(stamp_ns: int, p: Pose2) -> str:
    return (f"{stamp_ns / 1e9:.9f} {p[0]:.6f} {p[1]:.6f} 0.0 0.0 0.0 "
            f"{math.sin(p[2] / 2):.9f} {math.cos(p[2] / 2):.9f}\n")


class RunRecorder:
    """Subscribes to truth, odometry, corrections, observations, statuses and ticks."""

    def __init__(self, bus: Bus, keys: Keys, scenario: Scenario) -> None:
        self.s = scenario
        self.keys = keys
        self.a2m = arena_to_map(scenario)
        self.inboxes = {
            "truth": bus.subscribe(keys.truth()),
            "odom": bus.subscribe(keys.odometry()),
            "corr": bus.subscribe(keys.correction()),
            "obs": bus.subscribe(keys.observation()),
            "status": bus.subscribe(keys.robot_status()),
            "world": bus.subscribe(keys.world_status()),
            "server": bus.subscribe(keys.server_status()),
            "tick": bus.subscribe(keys.tick(), newest_only=True),
            "reloc": bus.subscribe(keys.relocalisation()),
            "wcmd": bus.subscribe(keys.world_command()),
            "applied": bus.subscribe(keys.world_applied()),
        }
        self.truth: dict[int, list[tuple[int, Pose2]]] = defaultdict(list)
        self.odom: dict[int, list[tuple[int, Pose2]]] = defaultdict(list)
        self.fused: dict[int, list[tuple[int, Pose2]]] = defaultdict(list)
        self.fused_cov: dict[int, list[tuple[int, tuple[float, ...]]]] = defaultdict(list)
        self.relocalisations: list[m.Relocalisation] = []
        #: (command, simulation time of its arrival here in ns: a tool may not know the sim time)
        self.world_commands: list[tuple[m.WorldCommand, int]] = []
        self.applied: list[m.WorldCommand] = []  # what the world applied of them and of the events
        # stamp, observer, kind, target, x, y, yaw and the upper triangle of the measurement's covariance
        self.observations: list[tuple[Any, ...]] = []
        self.modes: list[tuple[int, int, str]] = []
        self.counters: dict[str, dict[str, int]] = {}
        self.mode_now: dict[int, str] = {}
        self.sim_ns = 0
        self.rejected = 0
        self.run_id: str | None = None  # the world instance whose ticks set the clock
        #: newest stamp (sim ns) heard from each source ("world", "server", "agent/<k>"): a source that
        #: falls silent long before the run ends (a link lost under load) leaves its data incomplete
        self.last_heard: dict[str, int] = {}

    def _heard(self, who: str, stamp_ns: int) -> None:
        if stamp_ns > self.last_heard.get(who, -1):
            self.last_heard[who] = stamp_ns

    def poll(self) -> None:
        """Drain every inbox into the in-memory record."""
        ib = self.inboxes
        for it in ib["tick"].drain():
            tick = self._decode(m.Tick, it.value)
            if tick is not None and self.run_id in (None, tick.run_id):
                self.run_id = tick.run_id
                self.sim_ns = max(self.sim_ns, tick.stamp_ns)
            elif tick is not None:
                self.rejected += 1  # a tick of another world instance must not move our clock
        for it in ib["truth"].drain():
            t = self._decode(m.GroundTruthPose, it.value, it.key)
            if t is not None:
                self.truth[t.robot_id].append((t.stamp_ns, se2_compose(self.a2m, (t.x_m, t.y_m, t.yaw_rad))))
                self.sim_ns = max(self.sim_ns, t.stamp_ns)
                self._heard("world", t.stamp_ns)
        for it in ib["odom"].drain():
            o = self._decode(m.OdometryEstimate, it.value, it.key)
            if o is not None:
                self.odom[o.robot_id].append((o.stamp_ns, (o.x_m, o.y_m, o.yaw_rad)))
                self._heard(f"agent/{o.robot_id}", o.stamp_ns)
        for it in ib["corr"].drain():
            c = self._decode(m.Correction, it.value, it.key)
            if c is not None:
                self._heard("server", c.stamp_ns)
            # a robot whose odometry stopped (its agent gone) keeps its last stamp: one pose per instant
            if c is not None and c.localised and (not self.fused[c.robot_id]
                                                  or c.pose_time_ns != self.fused[c.robot_id][-1][0]):
                self.fused[c.robot_id].append((c.pose_time_ns, (c.x_m, c.y_m, c.yaw_rad)))
                self.fused_cov[c.robot_id].append((c.pose_time_ns, tuple(c.cov)))
        for it in ib["obs"].drain():
            ob = self._decode(m.RelativeObservation, it.value, it.key)
            if ob is not None:
                c = ob.cov  # 3x3 row-major (the decoder rejects any other)
                self.observations.append((ob.stamp_ns, ob.robot_id, ob.target_kind, ob.target_id, ob.x_m, ob.y_m,
                                          ob.yaw_rad, c[0], c[1], c[2], c[4], c[5], c[8]))
        for it in ib["reloc"].drain():
            rl = self._decode(m.Relocalisation, it.value)
            if rl is not None and self._known(rl.robot_id):
                self.relocalisations.append(rl)
        for it in ib["wcmd"].drain():
            wc = self._decode(m.WorldCommand, it.value)
            if wc is not None and self._known(wc.robot_id):
                self.world_commands.append((wc, self.sim_ns))
        for it in ib["applied"].drain():
            wc = self._decode(m.WorldCommand, it.value)
            if wc is not None and self._known(wc.robot_id):
                self.applied.append(wc)
        for name in ("status", "world", "server"):
            for it in ib[name].drain():
                st = self._decode(m.AgentStatus, it.value, it.key if name == "status" else None)
                if st is None:
                    continue
                who = f"agent/{st.robot_id}" if st.role == "agent" else st.role
                self.counters[who] = dict(st.counters)
                self._heard(who, st.stamp_ns)
                if st.role == "agent" and st.robot_id is not None:
                    self.modes.append((st.stamp_ns, st.robot_id, st.mode))
                    self.mode_now[st.robot_id] = st.mode

    def _decode(self, cls: Any, payload: bytes, robot_key: str | None = None) -> Any:
        """The message, or None (counted) if it does not decode or, on a robot's key
        (``robot_key``), carries another robot id or one not in the roster."""
        try:
            msg = codec.decode(cls, payload)
        except codec.DecodeError:
            self.rejected += 1
            return None
        if robot_key is not None and (msg.robot_id != self.keys.robot_id_of(robot_key)
                                      or msg.robot_id not in self.s.robot_ids):
            self.rejected += 1
            return None
        return msg

    def _known(self, robot_id: int) -> bool:
        if robot_id in self.s.robot_ids:
            return True
        self.rejected += 1
        return False

    def fused_error(self, rid: int) -> float | None:
        """Distance (m) between the newest fused pose and the truth at that time."""
        if not self.fused.get(rid) or not self.truth.get(rid):
            return None
        stamp, p = self.fused[rid][-1]
        for t, q in reversed(self.truth[rid]):
            if t <= stamp:
                return math.hypot(p[0] - q[0], p[1] - q[1])
        return None

    def write(self, run_dir: Path, info: dict[str, Any]) -> None:
        """Write trajectories (with ``fused_cov_<k>.csv``), observations.csv, modes.csv,
        relocalisations.csv, world_commands.csv, interventions.csv and run.json."""
        traj = run_dir / "trajectories"
        traj.mkdir(parents=True, exist_ok=True)
        for rid in self.s.robot_ids:
            truth = self.truth.get(rid, [])
            with open(traj / f"truth_{rid}.tum", "w") as f:
                f.writelines(_tum_line(t, p) for t, p in truth)
            start = truth[0][1] if truth else None
            with open(traj / f"odom_{rid}.tum", "w") as f:
                if start is not None:
                    f.writelines(_tum_line(t, se2_compose(start, p)) for t, p in self.odom.get(rid, []))
            with open(traj / f"fused_{rid}.tum", "w") as f:
                f.writelines(_tum_line(t, p) for t, p in self.fused.get(rid, []))
            with open(traj / f"fused_cov_{rid}.csv", "w", newline="") as f:
                w = csv.writer(f)
                w.writerow(FUSED_COV_HEADER)
                w.writerows([t, *(repr(float(v)) for v in cov)] for t, cov in self.fused_cov.get(rid, [])
                            if len(cov) == 9)
        with open(run_dir / "observations.csv", "w", newline="") as f:
            w = csv.writer(f)
            w.writerow([*OBS_HEADER, *OBS_COV_COLUMNS])
            w.writerows(sorted(self.observations))  # arrival order across agents is not deterministic
        with open(run_dir / "modes.csv", "w", newline="") as f:
            w = csv.writer(f)
            w.writerow(["stamp_ns", "robot", "mode"])
            w.writerows(sorted(self.modes))
        with open(run_dir / "relocalisations.csv", "w", newline="") as f:
            w = csv.writer(f)
            w.writerow(RELOC_HEADER)
            w.writerows([r.stamp_ns, r.robot_id, f"{r.jump_m:.6f}", f"{r.from_x_m:.6f}", f"{r.from_y_m:.6f}",
                         f"{r.from_yaw_rad:.6f}", f"{r.to_x_m:.6f}", f"{r.to_y_m:.6f}", f"{r.to_yaw_rad:.6f}",
                         r.evidence, " ".join(str(o) for o in r.observers)]
                        for r in sorted(self.relocalisations, key=lambda r: (r.stamp_ns, r.robot_id)))
        with open(run_dir / "world_commands.csv", "w", newline="") as f:
            w = csv.writer(f)
            w.writerow(WORLD_COMMANDS_HEADER)
            w.writerows([c.stamp_ns, c.robot_id, c.action, f"{c.x_m:.6f}", f"{c.y_m:.6f}", f"{c.yaw_rad:.6f}", rx]
                        for c, rx in sorted(self.world_commands, key=lambda e: (e[0].stamp_ns, e[0].robot_id)))
        with open(run_dir / "interventions.csv", "w", newline="") as f:
            w = csv.writer(f)
            w.writerow(INTERVENTIONS_HEADER)
            w.writerows([c.stamp_ns, c.robot_id, c.action, f"{c.x_m:.6f}", f"{c.y_m:.6f}", f"{c.yaw_rad:.6f}"]
                        for c in sorted(self.applied, key=lambda c: (c.stamp_ns, c.robot_id)))
        run = {"scenario": msgspec.to_builtins(self.s), "robots": list(self.s.robot_ids),
               "origin_id": self.s.map.origin_id, "clock": self.s.clock.mode, "sim_time_s": self.sim_ns / 1e9,
               "counters": self.counters,
               "last_heard_s": {who: ns / 1e9 for who, ns in sorted(self.last_heard.items())}, **info}
        (run_dir / "run.json").write_text(json.dumps(run, indent=2))

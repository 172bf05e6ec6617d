"""Column headers of the run folder's newer CSV files, shared by the writer
(:mod:`tagswarm.recording.runrecorder`) and the reader (:mod:`tagswarm.evaluation.runfolder`) without
importing either's dependencies (Zenoh on one side, evo on the other).

- ``trajectories/fused_cov_<k>.csv`` (:data:`FUSED_COV_HEADER`): one row per fused
  pose of ``fused_<k>.tum``: ``stamp_ns`` and the row-major 3x3 covariance of
  (x_m, y_m, yaw_rad) as the server published it, in the robot's own axes (see
  :mod:`tagswarm.evaluation.covframe`); m², m·rad, rad².
- ``observations.csv``: :data:`OBS_HEADER`, then (newer) :data:`OBS_COV_COLUMNS`, the upper
  triangle of the covariance the observer sent with each measurement (x_m, y_m, yaw_rad in its
  own base axes; m², m·rad, rad²; empty or NaN when it sent none).
- ``relocalisations.csv`` (:data:`RELOC_HEADER`): the server's
  :class:`~tagswarm.protocol.messages.Relocalisation` events; poses in the MAP frame (m,
  rad); ``observers`` space-separated robot ids (``-1`` = a landmark).
- ``world_commands.csv`` (:data:`WORLD_COMMANDS_HEADER`): the
  :class:`~tagswarm.protocol.messages.WorldCommand` messages seen on the network (kidnaps:
  teleport to / push by (x_m, y_m, yaw_rad), ARENA frame); ``received_ns`` is the
  recorder's simulation time when it arrived (a tool may stamp 0).
- ``interventions.csv`` (:data:`INTERVENTIONS_HEADER`): what the world applied of them and of
  the scenario's ``[[events]]`` (``world/applied``), stamped with the step it applied them at;
  refused ones are not in it.  Its absence marks a run folder older than it.
"""

from __future__ import annotations

from typing import Final

OBS_HEADER: Final = ("stamp_ns", "observer", "target_kind", "target_id", "x_m", "y_m", "yaw_rad")
OBS_COV_COLUMNS: Final = ("cov_xx", "cov_xy", "cov_xyaw", "cov_yy", "cov_yyaw", "cov_yawyaw")
FUSED_COV_HEADER: Final = ("stamp_ns", *(f"c{i}{j}" for i in range(3) for j in range(3)))
RELOC_HEADER: Final = ("stamp_ns", "robot_id", "jump_m", "from_x_m", "from_y_m", "from_yaw_rad", "to_x_m", "to_y_m",
                       "to_yaw_rad", "evidence", "observers")
WORLD_COMMANDS_HEADER: Final = ("stamp_ns", "robot_id", "action", "x_m", "y_m", "yaw_rad", "received_ns")
INTERVENTIONS_HEADER: Final = ("stamp_ns", "robot_id", "action", "x_m", "y_m", "yaw_rad")

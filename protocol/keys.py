"""Every Zenoh key expression of tagswarm; no other module spells a key.

Layout (``<run>`` isolates runs sharing one network)::

    tagswarm/<run>/world/tick                       Tick
    tagswarm/<run>/world/ack/<role>/<id>            TickAck
    tagswarm/<run>/world/render/<worker>            RenderPoses (world -> worker)
    tagswarm/<run>/world/status                     AgentStatus of the world
    tagswarm/<run>/world/command                    WorldCommand (teleport / push a robot)
    tagswarm/<run>/world/applied                    WorldCommand (one the world applied, stamped then)
    tagswarm/<run>/robot/<id>/camera/<name>         CameraImage
    tagswarm/<run>/robot/<id>/encoders              EncoderTicks
    tagswarm/<run>/robot/<id>/cmd                   WheelCommand
    tagswarm/<run>/robot/<id>/recorded_cmd          WheelCommand (a replay's recorded commands)
    tagswarm/<run>/robot/<id>/truth                 GroundTruthPose (evaluation only)
    tagswarm/<run>/robot/<id>/observation           RelativeObservation
    tagswarm/<run>/robot/<id>/odometry              OdometryEstimate
    tagswarm/<run>/robot/<id>/correction            Correction
    tagswarm/<run>/robot/<id>/goal                  Goal
    tagswarm/<run>/robot/<id>/status                AgentStatus
    tagswarm/<run>/server/map                       GlobalMap (also a queryable)
    tagswarm/<run>/server/status                    AgentStatus of the server
    tagswarm/<run>/server/relocalisation            Relocalisation events
    tagswarm/<run>/deploy/claim                     ClaimReply (a query: compose agents claim a robot id)
    tagswarm/<run>/alive/<role>/<id>                liveliness tokens
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from typing import Final

from tagswarm.protocol.errors import UsageError

_RUN_RE: Final = re.compile(r"[A-Za-z0-9_.-]{1,64}")
_NAME_RE: Final = re.compile(r"[A-Za-z0-9_.-]{1,64}")
_ID_RE: Final = re.compile(r"0|[1-9][0-9]{0,5}")
ROOT: Final = "tagswarm"


class KeyNameError(UsageError, ValueError):
    """A run id, role or camera name that cannot be part of a key."""


def check_name(value: str, what: str) -> str:
    """Return ``value`` if it is a safe single key chunk, else raise :class:`KeyNameError`."""
    if not _NAME_RE.fullmatch(value):
        raise KeyNameError(f"{what} {value!r} must be 1-64 characters of letters, digits, '_', '.', '-'")
    return value


@dataclass(frozen=True)
class Keys:
    """Key expressions of one run."""

    run: str

    def __post_init__(self) -> None:
        if not _RUN_RE.fullmatch(self.run):
            raise KeyNameError(f"run id {self.run!r} must be 1-64 characters of letters, digits, '_', '.', '-'")

    @property
    def prefix(self) -> str:
        return f"{ROOT}/{self.run}"

    def all(self) -> str:
        """Every key of this run."""
        return f"{self.prefix}/**"

    # -- world ---------------------------------------------------------------
    def tick(self) -> str:
        return f"{self.prefix}/world/tick"

    def ack(self, participant: str) -> str:
        role, ident = split_participant(participant)
        return f"{self.prefix}/world/ack/{role}/{ident}"

    def acks(self) -> str:
        return f"{self.prefix}/world/ack/*/*"

    def render(self, worker: int) -> str:
        return f"{self.prefix}/world/render/{worker}"

    def world_status(self) -> str:
        return f"{self.prefix}/world/status"

    def world_command(self) -> str:
        return f"{self.prefix}/world/command"

    def world_applied(self) -> str:
        """Each intervention (world command or scenario event) the world applied, at the step it did."""
        return f"{self.prefix}/world/applied"

    # -- robots --------------------------------------------------------------
    def robot(self, robot_id: int) -> str:
        return f"{self.prefix}/robot/{int(robot_id)}"

    def image(self, robot_id: int, camera: str) -> str:
        return f"{self.robot(robot_id)}/camera/{check_name(camera, 'camera name')}"

    def images(self, robot_id: int | None = None) -> str:
        """All cameras of one robot, or of every robot."""
        rid = "*" if robot_id is None else str(int(robot_id))
        return f"{self.prefix}/robot/{rid}/camera/*"

    def encoders(self, robot_id: int | None = None) -> str:
        return self._robot_leaf(robot_id, "encoders")

    def cmd(self, robot_id: int | None = None) -> str:
        return self._robot_leaf(robot_id, "cmd")

    def recorded_cmd(self, robot_id: int | None = None) -> str:
        """A replay's copy of the wheel commands the robot drove with when it was recorded."""
        return self._robot_leaf(robot_id, "recorded_cmd")

    def truth(self, robot_id: int | None = None) -> str:
        return self._robot_leaf(robot_id, "truth")

    def observation(self, robot_id: int | None = None) -> str:
        return self._robot_leaf(robot_id, "observation")

    def odometry(self, robot_id: int | None = None) -> str:
        return self._robot_leaf(robot_id, "odometry")

    def correction(self, robot_id: int | None = None) -> str:
        return self._robot_leaf(robot_id, "correction")

    def goal(self, robot_id: int | None = None) -> str:
        return self._robot_leaf(robot_id, "goal")

    def robot_status(self, robot_id: int | None = None) -> str:
        return self._robot_leaf(robot_id, "status")

    def _robot_leaf(self, robot_id: int | None, leaf: str) -> str:
        rid = "*" if robot_id is None else str(int(robot_id))
        return f"{self.prefix}/robot/{rid}/{leaf}"

    # -- server --------------------------------------------------------------
    def map(self) -> str:
        return f"{self.prefix}/server/map"

    def server_status(self) -> str:
        return f"{self.prefix}/server/status"

    def relocalisation(self) -> str:
        return f"{self.prefix}/server/relocalisation"

    def claim(self) -> str:
        """Where an agent container asks the claim authority for a free robot id (a query)."""
        return f"{self.prefix}/deploy/claim"

    # -- presence ------------------------------------------------------------
    def alive(self, participant: str) -> str:
        role, ident = split_participant(participant)
        return f"{self.prefix}/alive/{role}/{ident}"

    def alive_role(self, role: str) -> str:
        """Liveliness tokens of every process of one role."""
        return f"{self.prefix}/alive/{check_name(role, 'role')}/*"

    def alive_all(self) -> str:
        return f"{self.prefix}/alive/**"

    # -- parsing -------------------------------------------------------------
    def robot_id_of(self, key: str) -> int | None:
        """Robot id in a ``.../robot/<id>/...`` key of this run, else ``None``."""
        head = f"{self.prefix}/robot/"
        if not key.startswith(head):
            return None
        chunk = key[len(head) :].split("/", 1)[0]
        if not _ID_RE.fullmatch(chunk):
            return None
        return int(chunk)

    def participant_of(self, key: str) -> str | None:
        """``"role/id"`` of an ack or liveliness key of this run, else ``None``."""
        for head in (f"{self.prefix}/world/ack/", f"{self.prefix}/alive/"):
            if key.startswith(head):
                rest = key[len(head) :].split("/")
                if len(rest) == 2 and all(_NAME_RE.fullmatch(p) for p in rest):
                    return f"{rest[0]}/{rest[1]}"
        return None


def split_participant(participant: str) -> tuple[str, str]:
    """Split ``"role/id"`` into its two chunks, validating both."""
    parts = participant.split("/")
    if len(parts) != 2:
        raise KeyNameError(f"participant {participant!r} must look like 'role/id', e.g. 'agent/0'")
    return check_name(parts[0], "role"), check_name(parts[1], "participant id")

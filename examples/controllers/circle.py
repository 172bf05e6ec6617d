"""Drive in circles: the smallest useful tagswarm controller.

The robot drives a circle of radius ``RADIUS_M`` counter-clockwise (turning
left) at ``SPEED_M_S``, starting from wherever it stands, and at half that
speed (the same circle) while the server has not localised it yet.  Collision
avoidance stays on (``avoid`` is inherited as True): if the circle would bring
it too close to another robot or a wall, the agent bends the command away.

Run it on robot 3 of the paper scenario (docs/controllers.md)::

    tagswarm up --clock lockstep --duration 20 --agent-module examples/controllers/circle.py:3

or by module name, with ``examples/`` on the agent's ``PYTHONPATH``::

    PYTHONPATH=examples tagswarm up --agent-module controllers.circle:3

Everything else of the agent (tag detection, observations, odometry, the
server's corrections) runs as for any robot, so the robot is localised like
the others while it circles.
"""

from __future__ import annotations

from tagswarm.agents.controller import ControlInput, Controller, ControllerConfig, Twist

SPEED_M_S = 0.1
RADIUS_M = 0.15


class Circle(Controller):
    """A constant twist: ``speed_m_s`` forward on a circle of ``radius_m`` (left turn if positive)."""

    mode = "circle"  # shown as this robot's mode in the live view and modes.csv

    def __init__(self, speed_m_s: float = SPEED_M_S, radius_m: float = RADIUS_M) -> None:
        self.speed_m_s = speed_m_s
        self.radius_m = radius_m

    def step(self, inputs: ControlInput) -> Twist:
        v = self.speed_m_s if inputs.localised else self.speed_m_s / 2
        return Twist(v_m_s=v, w_rad_s=v / self.radius_m)


def make_controller(config: ControllerConfig) -> Controller:
    """The contract of ``--agent-module``: called once per run with this robot's config."""
    return Circle(speed_m_s=min(SPEED_M_S, config.agent.max_speed_m_s))

"""Tick.cameras_of: the ``"robot/camera"`` pairs of a tick by robot (agent and server read them alike)."""

from __future__ import annotations

from tagswarm.protocol import messages as m


def test_cameras_of_groups_the_rendered_pairs_by_robot_and_skips_malformed_ones() -> None:
    tick = m.Tick(seq=0, stamp_ns=100, run_id="r", step=1, dt_ns=10, mode="lockstep",
                  cameras_rendered=("0/front", "0/back", "12/front", "front", "x/front"))
    assert tick.cameras_of() == {0: {"front", "back"}, 12: {"front"}}
    assert m.Tick(seq=0, stamp_ns=0, run_id="r", step=0, dt_ns=1, mode="lockstep").cameras_of() == {}

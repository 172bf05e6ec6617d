"""An agent's input checks (tagswarm.agents.intake): other robots' messages, encoders of another
resolution and data of another world run never reach odometry or vision, and are counted."""

from __future__ import annotations

import logging
from collections import Counter

from tagswarm.agents.intake import AgentIntake
from tagswarm.protocol import codec
from tagswarm.protocol import messages as m
from tagswarm.protocol.bus import Received
from tagswarm.protocol.keys import Keys
from tagswarm.runtime import streams

KEYS = Keys("t")


def _intake() -> tuple[AgentIntake, streams.RejectCounter, Counter[str]]:
    rejects, counters = streams.RejectCounter(logging.getLogger("test")), Counter[str]()
    return AgentIntake(1, 4096, rejects, counters), rejects, counters


def _enc(stamp_ns: int, robot: int = 1, tpr: int = 4096) -> Received[bytes]:
    return Received(KEYS.encoders(1), codec.encode(m.EncoderTicks(seq=0, stamp_ns=stamp_ns, robot_id=robot,
                                                                  left_ticks=stamp_ns, right_ticks=0,
                                                                  ticks_per_rev=tpr)))


def _img(stamp_ns: int, robot: int = 1, camera: str = "front") -> Received[bytes]:
    return Received(KEYS.image(1, "front"), codec.encode(m.CameraImage(
        seq=0, stamp_ns=stamp_ns, robot_id=robot, camera=camera, step=0, width=2, height=1, fx_px=1.0, fy_px=1.0,
        cx_px=1.0, cy_px=0.5, mount=m.Pose3(x_m=0.0, y_m=0.0, z_m=0.5), data=b"\x00\x00")))


def test_encoders_keep_order_and_drop_other_robots_resolutions_and_runs() -> None:
    intake, rejects, counters = _intake()
    got = [e.stamp_ns for _, e in intake.encoders([_enc(10), _enc(20, robot=2), _enc(30, tpr=1024), _enc(40), _enc(5)])]
    assert got == [10, 40]
    assert rejects.counts == {"spoofed": 1, "inconsistent": 1} and counters["stale_encoders"] == 1
    # a new run starts at tick 15: counts stamped after it are of the old run, the older ones are taken
    intake.reset()
    assert [e.stamp_ns for _, e in intake.encoders([_enc(12), _enc(50)], upto_ns=15)] == [12]
    assert counters["stale_encoders"] == 2


def test_frames_of_another_robot_or_camera_and_older_frames_are_dropped() -> None:
    intake, rejects, counters = _intake()
    frames = [_img(100), _img(200, robot=3), _img(300, camera="back"), _img(50), _img(400)]
    assert [f.stamp_ns for f in intake.frames("front", frames)] == [100, 400]
    assert rejects.counts == {"spoofed": 2} and counters["stale_frames"] == 1


def test_corrections_and_goals_for_another_robot_are_spoofed() -> None:
    intake, rejects, _ = _intake()
    goals = [Received(KEYS.goal(1), codec.encode(m.Goal(seq=0, stamp_ns=0, robot_id=r, x_m=1.0, y_m=2.0)))
             for r in (1, 2)]
    assert [g.robot_id for _, g in intake.own(goals, m.Goal)] == [1]
    assert rejects.counts == {"spoofed": 1}


def test_a_correction_lapses_only_for_a_sigma_grown_past_the_claim() -> None:
    from tagswarm.agents.intake import sigma_lapsed

    def corr(cov: tuple[float, ...], localised: bool = False) -> m.Correction:
        return m.Correction(seq=1, stamp_ns=1, robot_id=1, map_odom_x_m=0.0, map_odom_y_m=0.0, map_odom_yaw_rad=0.0,
                            x_m=0.0, y_m=0.0, yaw_rad=0.0, cov=cov, last_fix_ns=0, localised=localised)

    assert sigma_lapsed(corr((0.36, 0, 0, 0, 0.01, 0, 0, 0, 0.01)), 0.5)  # sigma 0.6 m along x
    assert not sigma_lapsed(corr((0.01, 0, 0, 0, 0.01, 0, 0, 0, 0.01)), 0.5)  # sigma 0.1 m: a dispute
    assert not sigma_lapsed(corr((0.36, 0, 0, 0, 0.01, 0, 0, 0, 0.01), localised=True), 0.5)  # vouched for
    # the worst axis, as the server judges it: 0.2 m^2 on each axis, correlated 0.9, is 0.62 m along the diagonal
    assert sigma_lapsed(corr((0.2, 0.18, 0, 0.18, 0.2, 0, 0, 0, 0.01)), 0.5)

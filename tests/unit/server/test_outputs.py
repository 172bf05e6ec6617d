"""Which realtime corrections the server sends and what time they carry (server/outputs.py:
correction_due, correction)."""

from __future__ import annotations

import math

import msgspec
import numpy as np

from tagswarm.protocol import messages as m
from tagswarm.server.fusion import Fusion, FusionParams
from tagswarm.server.outputs import CORRECTION_KEEPALIVE_NS, correction, correction_due, global_map


def corr(stamp_ns: int, x: float = 1.0, yaw: float = 0.0, fix: int = 0, localised: bool = True) -> m.Correction:
    return m.Correction(seq=0, stamp_ns=stamp_ns, robot_id=1, map_odom_x_m=x, map_odom_y_m=2.0,
                        map_odom_yaw_rad=yaw, x_m=0.0, y_m=0.0, yaw_rad=0.0, cov=(0.0,) * 9, localised=localised,
                        last_fix_ns=fix)


def test_the_first_correction_a_new_fix_and_a_change_of_localisation_always_go_out() -> None:
    last = corr(1_000_000_000)
    assert correction_due(None, last)
    assert correction_due(last, corr(1_020_000_000, fix=1_000_000_000))
    assert correction_due(last, corr(1_020_000_000, localised=False))


def test_an_unchanged_map_to_odom_waits_for_the_keepalive() -> None:
    last = corr(1_000_000_000)
    assert not correction_due(last, corr(1_020_000_000, x=1.0005, yaw=0.0005))
    assert not correction_due(last, corr(1_000_000_000 + CORRECTION_KEEPALIVE_NS - 1))
    assert correction_due(last, corr(1_000_000_000 + CORRECTION_KEEPALIVE_NS))


def test_a_moved_map_to_odom_goes_out_at_once_and_a_turn_wraps() -> None:
    last = corr(1_000_000_000, yaw=3.1415)
    assert correction_due(last, corr(1_020_000_000, x=1.002, yaw=3.1415))
    assert correction_due(last, corr(1_020_000_000, yaw=-3.1395))  # 2.8 mrad across the wrap
    assert not correction_due(last, corr(1_020_000_000, yaw=-3.14165))  # 0.3 mrad across it


def test_a_restarted_worlds_earlier_clock_sends_at_once() -> None:
    last = corr(5_000_000_000)
    assert correction_due(last, msgspec.structs.replace(last, stamp_ns=33_000_000))


def test_a_corrections_pose_is_stamped_with_the_robots_newest_odometry_not_the_servers_clock() -> None:
    """Robot 1 drives at 0.3 m/s in view of the origin; its odometry from 3.0 s on is late (a realtime
    link retransmitting) while the origin's keeps the clock at 3.5 s.  The fused pose is robot 1's at
    its newest odometry applied, so that is its stamp: at the clock's, it read 15 cm off."""
    fusion = Fusion(FusionParams(), 0, (0, 1))
    cov = np.diag([0.01**2, 0.01**2, 0.01**2])
    dt = round(1e9 / 30)
    for k in range(106):
        t = k * dt
        fusion.add_odometry(0, t, (0.0, 0.0, 0.0), 0.0)
        if t < 3_000_000_000:
            x = 0.3 * t / 1e9
            fusion.add_odometry(1, t, (x, 0.0, 0.0), x)
            if k % 3 == 0:
                fusion.add_observation(0, 1, t, (1.0 + x, 0.0, 0.0), cov)  # type: ignore[arg-type]
        fusion.advance(t)
    late_ns = fusion.latest_odom_ns(1)
    assert 2.9e9 < late_ns < 3.0e9 and fusion.watermark_ns > 3.4e9
    c = correction(fusion, 1, fusion.watermark_ns, 0)
    # the message is the server's clock's (a lockstep agent waits for each tick's), the pose is older
    assert c.localised and c.stamp_ns == fusion.watermark_ns and c.pose_stamp_ns == c.pose_time_ns == late_ns
    assert math.isclose(c.x_m, 1.0 + 0.3 * late_ns / 1e9, abs_tol=0.01)  # where it was then
    assert correction(fusion, 0, fusion.watermark_ns, 0).pose_time_ns == fusion.watermark_ns
    # the map has every robot's pose at its own time too
    entries = {e.robot_id: e for e in global_map(fusion, (0, 1), 0, fusion.watermark_ns, {}, {0, 1}, 0).robots}
    assert entries[1].pose_stamp_ns == late_ns and entries[0].pose_stamp_ns == fusion.watermark_ns
    # an old sender's correction without the field: the pose is at stamp_ns
    assert msgspec.structs.replace(c, pose_stamp_ns=0).pose_time_ns == fusion.watermark_ns
    assert entries[1].pose_time_at(fusion.watermark_ns) == late_ns
    assert msgspec.structs.replace(entries[1], pose_stamp_ns=0).pose_time_at(123) == 123  # an old map: its stamp

"""Which realtime corrections the server sends (server/outputs.py: correction_due)."""

from __future__ import annotations

import msgspec

from tagswarm.protocol import messages as m
from tagswarm.server.outputs import CORRECTION_KEEPALIVE_NS, correction_due


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

"""First placement of a robot (server/placement.py): agreement and choice."""

from __future__ import annotations

from tagswarm.server.noise import FusionParams
from tagswarm.server.placement import Candidate, choose

P = FusionParams()


def cand(x: float, y: float, trace: float, stamp: int = 0) -> Candidate:
    return Candidate(stamp, (x, y, 0.0), trace, ())


def test_waits_for_init_min_agreeing_candidates() -> None:
    assert choose([cand(1, 1, 1e-3), cand(1.01, 1, 1e-3)], P) is None
    # three, but one 27 cm off (a frontal face's yaw levered by the range): only two agree
    assert choose([cand(1, 1, 1e-3), cand(1.01, 1, 1e-3), cand(1.09, 0.75, 1e-5)], P) is None


def test_the_most_certain_agreeing_candidate_wins_and_an_outlier_is_left_out() -> None:
    good = [cand(2.727, 0.913, 2e-4), cand(2.775, 0.760, 5e-3), cand(2.719, 0.914, 1e-4)]
    outlier = cand(2.790, 0.650, 1e-6)  # the most certain by its own claim, but it disagrees
    chosen = choose([*good, outlier], P)
    assert chosen is not None
    best, agree = chosen
    assert best is good[2]
    assert outlier not in agree and len(agree) == 3

"""The report's advice when the origin robot saw nobody and was seen only from afar."""

from __future__ import annotations

import numpy as np

from tagswarm.evaluation.anchoring import anchoring_note
from tagswarm.evaluation.runfolder import Observations


def _obs(rows: list[tuple[float, int, bool, int]]) -> Observations:
    """Observations from (t_s, observer, is_robot, target) rows."""
    return Observations(np.array([r[0] for r in rows], float), np.array([r[1] for r in rows], np.int64),
                        np.array([r[2] for r in rows], bool), np.array([r[3] for r in rows], np.int64),
                        np.zeros((len(rows), 3)))


def _range(m: float):  # type: ignore[no-untyped-def]
    return lambda a, b, t: m


def test_a_blind_origin_seen_only_from_afar_gets_advice_naming_its_observers() -> None:
    obs = _obs([(0.1 * k, 9, True, 0) for k in range(30)] + [(0.5, 2, True, 0), (3.0, 9, True, 4)])
    note = anchoring_note(obs, 0, _range(3.4))
    assert note is not None and "origin robot 0" in note and "nor later" in note
    assert note.index("robot 9 (30 views at 3.4 m)") < note.index("robot 2 (1 view at 3.4 m)")
    assert "landmarks" in note


def test_no_advice_when_the_origin_sees_someone_is_seen_close_or_landmarks_tie_the_map() -> None:
    far = [(0.1 * k, 9, True, 0) for k in range(30)]
    assert anchoring_note(_obs([*far, (2.0, 0, True, 9)]), 0, _range(3.4)) is None  # it saw robot 9 itself
    assert anchoring_note(_obs([*far, (2.0, 0, False, 200)]), 0, _range(3.4)) is None  # a landmark, itself
    assert anchoring_note(_obs(far), 0, _range(1.5)) is None  # seen from close by: its heading is held
    assert anchoring_note(_obs(far), 0, _range(3.4), landmarks=4) is None
    assert anchoring_note(_obs(far), 0, lambda a, b, t: None) is None  # no truth to judge by
    # its own sightings after the window do not help the start, and the note says it did see later
    late = anchoring_note(_obs([*far, (12.0, 0, True, 9)]), 0, _range(3.4))
    assert late is not None and "nor later" not in late


def test_an_origin_nobody_sees_and_that_sees_nobody_is_told_too() -> None:
    note = anchoring_note(_obs([(1.0, 3, True, 4), (2.0, 4, True, 3)]), 0, _range(2.0))
    assert note is not None and "nobody saw it" in note
    assert anchoring_note(_obs([]), 0, _range(2.0)) is None  # no observations at all: nothing to say

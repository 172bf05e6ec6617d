"""Whether a run's map frame was tied well: advice when the origin robot saw nobody.

The map frame is the origin robot's first pose.  An origin that sees no robot (and no
landmark) itself is tied to the swarm only by the others' views of its cube, and the
heading of a cube's face seen from 3 m is uncertain by about 10 degrees: every robot
then hangs on that heading, and a degree of it puts a robot 5 m away 9 cm off.  Nothing
in the fusion can do better with those views, so the report says so and what helps.
Pure code: observations and truth in, one sentence (or None) out.  Seconds, metres.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np

from tagswarm.evaluation.runfolder import Observations

#: the start of a run that the advice looks at (s): the first placements are made in it
ANCHOR_WINDOW_S = 10.0
#: views of the origin from this far (median per observer, m) leave its heading loose
FAR_VIEW_M = 2.5
#: what helps, in either note
REMEDY = ("give the origin a view of the swarm (face it towards the others, or move it into the open), "
          "or add wall landmarks ([[landmarks]])")


def anchoring_note(obs: Observations, origin: int, range_at: Callable[[int, int, float], float | None],
                   window_s: float = ANCHOR_WINDOW_S, landmarks: int = 0) -> str | None:
    """One line of advice when the origin robot ``origin`` made no sighting of its own in the
    first ``window_s`` seconds and was seen in them only from ``FAR_VIEW_M`` or more (median
    range per observer, from ``range_at(observer, target, t_s)``, the true distance, None if
    unknown); None otherwise, or when the scenario has ``landmarks`` (they tie the map to the
    arena whatever the origin sees)."""
    if landmarks > 0 or obs.stamp_s.size == 0:
        return None
    early = obs.stamp_s <= window_s
    if np.any(early & (obs.observer == origin)):
        return None
    of_origin = early & obs.is_robot & (obs.target_id == origin)
    own_total = int(np.sum(obs.observer == origin))
    later = "" if own_total else " (nor later in the run)"
    if not np.any(of_origin):
        return (f"the origin robot {origin} saw no robot in the first {window_s:.0f} s{later} and nobody saw it: "
                f"the map could not place anyone then; {REMEDY}")
    views: list[tuple[int, int, float]] = []  # (observer, count, median range m)
    for observer in sorted({int(o) for o in obs.observer[of_origin]}):
        pick = of_origin & (obs.observer == observer)
        ranges = [r for t in obs.stamp_s[pick]
                  if (r := range_at(observer, origin, float(t))) is not None and math.isfinite(r)]
        if ranges:  # an observer without a truth to judge by is left out
            views.append((observer, int(np.sum(pick)), float(np.median(ranges))))
    if not views or min(r for _, _, r in views) < FAR_VIEW_M:
        return None
    seen = ", ".join(f"robot {o} ({n} view{'s' if n != 1 else ''} at {r:.1f} m)"
                     for o, n, r in sorted(views, key=lambda v: -v[1])[:3])
    return (f"the origin robot {origin} saw no robot in the first {window_s:.0f} s{later} and was seen only from "
            f"afar: {seen}. The map's heading hangs on those views of its cube, whose yaw is uncertain by about "
            f"10 deg at 3 m, and 1 deg of it puts a robot 5 m away 9 cm off; {REMEDY}")

"""Decoys among a target's tags: a poster with one of a robot's tag IDs, seen beside the
robot or instead of the face it names, or a copy of its cube (pure code; docs/camera.md, Decoys).

:class:`DecoyResolver` is the part of :class:`tagswarm.agents.cubepose.CubePoseEstimator`
that decides which of a target's detections belong to it before its pose is trusted:
a tag ID seen twice in one image, or a set of tags that together fits no plausible
pose, is retried copy by copy / leaving one tag out; only an unambiguous answer is
kept, and what was dropped is counted as ``decoy``.  When what was dropped is itself a
plausible target (a second cube carrying copies of the target's IDs), the image shows
two robots of one identity and neither is trusted (``duplicate``) -- unless the map has
that robot within reach of exactly one of them (``resolved_by_map``; the others
count as ``decoy``): once the swarm is placed, a robot standing beside its copy is still
seen.  A copy cube seen
alone is indistinguishable from its robot in the images: the fusion server's gate and
its consistency test (server/recovery.py) keep it out of the map.  Frames and units as in
:mod:`tagswarm.agents.cubegeom`.
"""

from __future__ import annotations

import itertools
import math
from collections import Counter
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Final

from tagswarm.agents.cubegeom import CameraModel, PoseEstimate, TagGeom
from tagswarm.agents.detect import TagDetection
from tagswarm.agents.sixdof import Prior
from tagswarm.protocol.geometry import Pose2, se2_compose

# a target whose tag IDs repeat in an image is tried with at most this many choices of copies
_MAX_COPY_CHOICES: Final = 16
Member = tuple[int, TagGeom, TagDetection]  # (view index, the tag's geometry, its detection)


class DecoyResolver:
    """Which detections are the target (see the module docstring); the estimator supplies
    :meth:`_estimate_target` and its reject counts."""

    rejects: Counter[str]
    single_tag: bool
    #: where the map has each target: (x_m, y_m, radius_m) in the observer's base frame (set per estimate)
    expected: dict[tuple[str, int], tuple[float, float, float]]
    resolved_by_map: int  # copies of a target told apart by where the map has it
    #: the copies told apart from their target by the map in the last estimate: (key, x_m, y_m), base frame
    copies_seen: list[tuple[tuple[str, int], float, float]]

    def _reject(self, reason: str) -> None:
        self.rejects[reason] += 1

    def _estimate_target(self, key: tuple[str, int], members: list[Member],
                         views: list[tuple[CameraModel, list[TagDetection]]], prior: Prior) -> PoseEstimate | None:
        raise NotImplementedError

    def resolve(self, key: tuple[str, int], members: list[tuple[int, TagGeom, TagDetection]],
                        views: list[tuple[CameraModel, list[TagDetection]]], prior: Prior) -> PoseEstimate | None:
        """The target's estimate when one of its tag IDs shows more than once in an image (a decoy:
        a poster or a copy): every choice of one copy per repeated tag is tried; if exactly one
        choice gives a plausible pose it is the target and the other copies are counted as
        ``decoy``, otherwise the target is rejected as ``duplicate`` (no guessing).  Copies left
        out that are a plausible target on their own (a copy cube) reject it as ``duplicate`` too."""
        copies: dict[tuple[int, int], list[tuple[int, TagGeom, TagDetection]]] = {}
        for m in members:
            copies.setdefault((m[0], m[2].tag_id), []).append(m)
        repeated = [c for c in copies.values() if len(c) > 1]
        if not repeated:
            return self._without_stranger(key, members, views, prior)
        once = [c[0] for c in copies.values() if len(c) == 1]
        kept = self.rejects.copy()
        found = [(choice, est) for choice in itertools.islice(itertools.product(*repeated), _MAX_COPY_CHOICES)
                 if (est := self._estimate_target(key, once + list(choice), views, prior)) is not None]
        self.rejects = kept  # the trials' own rejects are not the target's
        if len(found) != 1:
            return self._by_map(key, [e for _, e in found], sum(len(c) - 1 for c in repeated))
        chosen, est = found[0]
        left = [m for c in repeated for m in c if not any(m is k for k in chosen)]
        others = self._also_a_target(key, left, views, prior)
        if others:
            return self._by_map(key, [est, *others], len(left))
        self.rejects["decoy"] += len(left)
        return est

    def _by_map(self, key: tuple[str, int], candidates: list[PoseEstimate], dropped: int) -> PoseEstimate | None:
        """Of two or more plausible copies of one target, the only one where the map has the target
        (``dropped`` detections of the others count as ``decoy``); None, counted as ``duplicate``,
        if the map does not have it or does not single one out."""
        exp = self.expected.get(key)
        near = [] if exp is None else [e for e in candidates if math.hypot(e.x_m - exp[0], e.y_m - exp[1]) <= exp[2]]
        if len(near) != 1:
            self._reject("duplicate")
            return None
        self.resolved_by_map += 1
        self.rejects["decoy"] += max(dropped, 1)
        self.copies_seen += [(key, e.x_m, e.y_m) for e in candidates if e is not near[0]]
        return near[0]

    def _also_a_target(self, key: tuple[str, int], left: list[Member],
                       views: list[tuple[CameraModel, list[TagDetection]]], prior: Prior) -> list[PoseEstimate]:
        """The plausible targets the detections ``left`` out of a target's estimate make on their own
        (one per image): a second cube carrying copies of the target's IDs (or the target itself
        beside such a copy).  Two plausible robots of one identity in one instant cannot be told
        apart from the images; a poster off the floor or tilted is no robot."""
        kept = self.rejects.copy()
        by_view: dict[int, list[Member]] = {}
        for m in left:
            by_view.setdefault(m[0], []).append(m)
        # one view at a time: copies left out of different images need not be one object
        alone = [e for ms in by_view.values() if (e := self._estimate_target(key, ms, views, prior)) is not None]
        self.rejects = kept
        return alone

    def _without_stranger(self, key: tuple[str, int], members: list[tuple[int, TagGeom, TagDetection]],
                          views: list[tuple[CameraModel, list[TagDetection]]], prior: Prior) -> PoseEstimate | None:
        """The target's estimate; when its tags together fit no plausible pose, each tag is left out
        in turn (a poster with one of the target's IDs while the target shows another face): if
        exactly one leave-one-out set fits, it is the target and the stranger counts as ``decoy``,
        otherwise the first failure's reason is counted as before."""
        kept = self.rejects.copy()
        est = self._estimate_target(key, members, views, prior)
        ids = {(m[0], m[2].tag_id) for m in members}
        if est is not None or len(members) < 2 or len(ids) != len(members) or self.single_tag:
            return est
        failed = self.rejects
        self.rejects = kept.copy()
        found = [(i, e) for i in range(len(members))
                 if (e := self._estimate_target(key, members[:i] + members[i + 1:], views, prior)) is not None]
        if len(found) != 1:
            self.rejects = failed
            return None
        self.rejects = kept
        i, est = found[0]
        others = self._also_a_target(key, [members[i]], views, prior)
        if others:
            return self._by_map(key, [est, *others], 1)
        self.rejects["decoy"] += 1
        return est


#: at most this many copy sites are remembered per target (a flood of them cannot grow memory)
MAX_COPY_SITES: Final = 8
#: a copy site not seen again beside its robot for this long (simulated) is forgotten: a site
#: filed while the map was wrong cannot hide the robot for good
COPY_SITE_TTL_NS: Final = 20_000_000_000


@dataclass
class CopySites:
    """Where this agent has seen a copy of a robot beside the robot itself (map frame): a robot
    cannot be in two places, so a later sighting of it at such a site, far from where the map
    has it, is the copy seen alone and is not published (the server would otherwise take an
    origin robot's repeated sightings of a static copy for a kidnap).  Sites closer than
    ``radius_m`` are one; a site lasts :data:`COPY_SITE_TTL_NS` after it was last seen."""

    radius_m: float = 0.3
    sites: dict[int, list[tuple[float, float, int]]] = field(default_factory=dict)

    def remember(self, me: Pose2, copies: Sequence[tuple[tuple[str, int], float, float]], now_ns: int) -> None:
        """Copies seen at ``now_ns`` from map pose ``me`` at (x_m, y_m) in our base frame."""
        for (kind, rid), x, y in copies:
            if kind != "robot":
                continue
            mx, my, _ = se2_compose(me, (x, y, 0.0))
            sites = [st for st in self.sites.get(rid, []) if math.hypot(mx - st[0], my - st[1]) >= self.radius_m]
            sites.append((mx, my, now_ns))  # a site seen again is refreshed where it was seen now
            self.sites[rid] = sites[-MAX_COPY_SITES:]

    def at(self, rid: int, x_m: float, y_m: float, now_ns: int) -> bool:
        """Whether map point (x_m, y_m) is a copy site of robot ``rid`` still remembered at ``now_ns``."""
        return any(math.hypot(x_m - sx, y_m - sy) < self.radius_m and now_ns - seen <= COPY_SITE_TTL_NS
                   for sx, sy, seen in self.sites.get(rid, ()))

"""Decoys among a target's tags: a poster with one of a robot's tag IDs, seen beside the
robot or instead of the face it names (pure code; docs/camera.md, Decoys).

:class:`DecoyResolver` is the part of :class:`tagswarm.agents.cubepose.CubePoseEstimator`
that decides which of a target's detections belong to it before its pose is trusted:
a tag ID seen twice in one image, or a set of tags that together fits no plausible
pose, is retried copy by copy / leaving one tag out; only an unambiguous answer is
kept, and what was dropped is counted as ``decoy``.  Frames and units as in
:mod:`tagswarm.agents.cubegeom`.
"""

from __future__ import annotations

import itertools
from collections import Counter
from typing import Final

from tagswarm.agents.cubegeom import CameraModel, PoseEstimate, TagGeom
from tagswarm.agents.detect import TagDetection
from tagswarm.agents.sixdof import Prior

# a target whose tag IDs repeat in an image is tried with at most this many choices of copies
_MAX_COPY_CHOICES: Final = 16
Member = tuple[int, TagGeom, TagDetection]  # (view index, the tag's geometry, its detection)


class DecoyResolver:
    """Which detections are the target (see the module docstring); the estimator supplies
    :meth:`_estimate_target` and its reject counts."""

    rejects: Counter[str]
    single_tag: bool

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
        ``decoy``, otherwise the target is rejected as ``duplicate`` (no guessing)."""
        copies: dict[tuple[int, int], list[tuple[int, TagGeom, TagDetection]]] = {}
        for m in members:
            copies.setdefault((m[0], m[2].tag_id), []).append(m)
        repeated = [c for c in copies.values() if len(c) > 1]
        if not repeated:
            return self._without_stranger(key, members, views, prior)
        once = [c[0] for c in copies.values() if len(c) == 1]
        kept = self.rejects.copy()
        found = [est for choice in itertools.islice(itertools.product(*repeated), _MAX_COPY_CHOICES)
                 if (est := self._estimate_target(key, once + list(choice), views, prior)) is not None]
        self.rejects = kept  # the trials' own rejects are not the target's
        if len(found) != 1:
            self._reject("duplicate")
            return None
        self.rejects["decoy"] += sum(len(c) - 1 for c in repeated)
        return found[0]

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
        found = [e for i in range(len(members))
                 if (e := self._estimate_target(key, members[:i] + members[i + 1:], views, prior)) is not None]
        if len(found) != 1:
            self.rejects = failed
            return None
        self.rejects = kept
        self.rejects["decoy"] += 1
        return found[0]

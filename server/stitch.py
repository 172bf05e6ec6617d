"""The paper's global-map stitching (pure code).

Pick an origin robot, give it pose (0, 0, 0), and place every other robot by
composing 2D homogeneous transforms along the chain of who-sees-whom.  An
observation (observer o sees target g at relative pose z, in o's base frame)
places g = o ⊕ z, or o = g ⊕ z⁻¹ when only g is placed.  Among all ways to reach
a robot the most certain chain wins (Dijkstra on the summed trace of the
observation covariances).  A robot that nobody sees and that sees nobody
placed is left out — never put at (0, 0).

This is the initial map of the fusion and the baseline the benchmarks compare
with.  Poses are (x_m, y_m, yaw_rad) in the map frame.
"""

from __future__ import annotations

import heapq
from collections.abc import Iterable, Mapping
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from tagswarm.protocol.geometry import Pose2, se2_compose, se2_inverse


@dataclass(frozen=True)
class Edge:
    """One relative observation: ``target``'s base in ``observer``'s base frame,
    with the (3, 3) covariance of (x_m, y_m, yaw_rad)."""

    observer: int
    target: int
    rel: Pose2
    cov: NDArray[np.float64]


def stitch(edges: Iterable[Edge], origin: int, anchors: Mapping[int, Pose2] | None = None) -> dict[int, Pose2]:
    """Place robots from relative observations.

    ``anchors`` are robots whose map poses are already known (default: just the
    origin at (0, 0, 0)).  Returns the map pose of every robot reachable from an
    anchor; unreachable robots are absent.
    """
    placed: dict[int, Pose2] = dict(anchors) if anchors else {origin: (0.0, 0.0, 0.0)}
    adj: dict[int, list[tuple[float, int, Pose2]]] = {}
    for e in edges:
        if e.observer == e.target:
            continue
        cost = float(np.trace(e.cov))
        adj.setdefault(e.observer, []).append((cost, e.target, e.rel))
        adj.setdefault(e.target, []).append((cost, e.observer, se2_inverse(e.rel)))
    heap: list[tuple[float, int, int, Pose2]] = []
    tie = 0
    for rid in placed:
        for cost, nb, rel in adj.get(rid, []):
            heapq.heappush(heap, (cost, tie, nb, se2_compose(placed[rid], rel)))
            tie += 1
    total: dict[int, float] = dict.fromkeys(placed, 0.0)
    while heap:
        cost, _, rid, pose = heapq.heappop(heap)
        if rid in placed:
            continue
        placed[rid] = pose
        total[rid] = cost
        for c, nb, rel in adj.get(rid, []):
            if nb not in placed:
                heapq.heappush(heap, (cost + c, tie, nb, se2_compose(pose, rel)))
                tie += 1
    return placed

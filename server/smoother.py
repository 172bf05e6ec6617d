"""The fusion's fixed-lag smoother (pure code, GTSAM): GTSAM's ``IncrementalFixedLagSmoother``
re-implemented over :class:`gtsam.ISAM2` so that one sequence of updates gives one result.

Why not GTSAM's own class: before it marginalises the variables that left the window it
asks iSAM2 to re-eliminate the cliques between them and the leaves, and GTSAM 4.3 gathers
those keys (``BayesTreeMarginalizationHelper``) in ``std::unordered_set`` s of clique
*pointers*, so the order in which the keys reach iSAM2 follows where the cliques happen to
lie in memory.  iSAM2's elimination order, hence the Bayes tree and the last bits of every
estimate, follow that order: the same journal replayed 40 times in one process gave one of
two results (35 : 5) at a step that marginalised 4 keys, and two lockstep runs of one scene
parted after 50 s.  Here the same keys are gathered (the same rule, read off the Bayes tree
iSAM2 exports as Graphviz text) and handed over sorted.

The interface is the subset of GTSAM's class the server uses, with GTSAM's method names.
Stamps are seconds of simulated time; a variable whose stamp is older than the newest
stamp minus the lag is marginalised at the end of an update (GTSAM's class: every update; here
in batches, see :class:`FixedLagSmoother`, because reading the tree costs ~14 ms at 16 robots).
"""

from __future__ import annotations

from collections import deque
from collections.abc import Iterable, Mapping

import gtsam
import numpy as np
from numpy.typing import NDArray

from tagswarm.protocol.errors import TagswarmError


class SmootherError(TagswarmError, RuntimeError):
    """iSAM2 refused an update (an indeterminate system, a variable that is not a leaf)."""


class BayesTree:
    """The cliques of an iSAM2 Bayes tree read from its Graphviz text (``ISAM2.dot`` with
    decimal keys): :meth:`frontals` (in elimination order), :meth:`parents` (the separator)
    and ``children``, a clique named by its node in that text."""

    @classmethod
    def of(cls, isam: gtsam.ISAM2) -> BayesTree:
        """The tree of ``isam`` (~0.5 ms for ~350 keys; reading it another ~0.3 ms)."""
        return cls(isam.dot(str))

    def __init__(self, dot: str) -> None:
        self.labels: dict[str, tuple[str, str]] = {}
        self.children: dict[str, list[str]] = {}
        # plain string splitting: regexes took 6x as long
        for line in dot.split("\n"):
            i = line.find('[label="')
            if i >= 0:
                frontals, _, parents = line[i + 8:line.rindex('"')].partition(":")
                self.labels[line[:i]] = (frontals, parents)
                continue
            a, arrow, b = line.partition("->")
            if arrow:
                self.children.setdefault(a, []).append(b.strip().rstrip(";"))
        self._frontals: dict[str, list[int]] = {}
        self._parents: dict[str, frozenset[int]] = {}

    def frontals(self, c: str) -> list[int]:
        f = self._frontals.get(c)
        if f is None:
            f = self._frontals[c] = [int(k) for k in self.labels[c][0].replace(",", " ").split()]
        return f

    def parents(self, c: str) -> frozenset[int]:
        p = self._parents.get(c)
        if p is None:
            p = self._parents[c] = frozenset(int(k) for k in self.labels[c][1].replace(",", " ").split())
        return p

    def owners(self, keys: Iterable[int]) -> dict[int, str]:
        """The clique of which each of ``keys`` is a frontal variable."""
        out: dict[int, str] = {}
        want: dict[str, int] = {}
        for k in keys:
            if str(k) in self.labels:  # a clique is named by its first frontal
                out[k] = str(k)
            else:
                want[str(k)] = k
        for c, (frontals, _) in self.labels.items():
            if not want:
                break
            if "," in frontals:
                for tok in frontals.replace(",", " ").split()[1:]:
                    if tok in want:
                        out[want.pop(tok)] = c
        return out


def keys_to_reeliminate(tree: BayesTree, marginal: Iterable[int]) -> list[int]:
    """The keys iSAM2 must re-eliminate so that every key of ``marginal`` becomes a leaf it can
    marginalise (GTSAM's ``BayesTreeMarginalizationHelper::gatherAdditionalKeysToReEliminate``),
    sorted.  A clique needs it when a kept variable precedes a marginal one among its frontals,
    or when a child depends on a marginal variable and holds kept ones below it; then so does
    every clique on a path from it down to kept variables."""
    ms = set(marginal)
    whole_clique: dict[str, bool] = {}
    whole_subtree: dict[str, bool] = {}

    def all_marginal(c: str) -> bool:
        if c not in whole_clique:
            whole_clique[c] = all(k in ms for k in tree.frontals(c))
        return whole_clique[c]

    def all_marginal_below(c: str) -> bool:
        if c not in whole_subtree:
            whole_subtree[c] = all_marginal(c) and all(all_marginal_below(ch) for ch in tree.children.get(c, ()))
        return whole_subtree[c]

    def needs(c: str) -> bool:
        kept_ahead = False
        for k in tree.frontals(c):
            if k not in ms:
                kept_ahead = True
            elif kept_ahead or any(k in tree.parents(ch) and not all_marginal_below(ch)
                                   for ch in tree.children.get(c, ())):
                return True
        return False

    owners = tree.owners(ms)
    order: dict[str, int] = {}
    for k in sorted(owners):
        order.setdefault(owners[k], len(order))
    chosen: set[str] = set()
    for c in order:  # first seen, in key order: nothing here depends on memory
        if c in chosen or not needs(c):
            continue
        chosen.add(c)
        queue = deque(ch for ch in tree.children.get(c, ()) if ch not in chosen and tree.parents(ch) & ms)
        while queue:
            d = queue.popleft()
            if not all_marginal_below(d):
                chosen.add(d)
                queue.extend(ch for ch in tree.children.get(d, ()) if ch not in chosen)
    return sorted({k for c in chosen for k in tree.frontals(c)})


class FixedLagSmoother:
    """iSAM2 over the variables of the last ``lag_s`` seconds (see the module docstring); with
    ``batch_s``, variables leave in batches once the oldest is ``batch_s`` older than the lag
    (the window then spans ``lag_s`` to ``lag_s + batch_s``)."""

    def __init__(self, lag_s: float, params: gtsam.ISAM2Params, batch_s: float = 0.0) -> None:
        self.lag_s = float(lag_s)
        self.batch_s = float(batch_s)
        self._params = params
        self.isam = gtsam.ISAM2(params)
        self._stamps: dict[int, float] = {}

    # GTSAM's names, so that this is a drop-in for the parts of IncrementalFixedLagSmoother in use
    def params(self) -> gtsam.ISAM2Params:
        return self._params

    def smootherLag(self) -> float:
        return self.lag_s

    def __contains__(self, key: object) -> bool:
        """Whether variable ``key`` is in the window."""
        return key in self._stamps

    def timestamps(self) -> dict[int, float]:
        """Key -> stamp (s) of every variable in the window."""
        return dict(self._stamps)

    def getFactors(self) -> gtsam.NonlinearFactorGraph:
        """The factors (empty slots where marginalisation removed some; the graph is iSAM2's own)."""
        return self.isam.getFactorsUnsafe()

    def getLinearizationPoint(self) -> gtsam.Values:
        return self.isam.getLinearizationPoint()

    def calculateEstimate(self) -> gtsam.Values:
        return self.isam.calculateEstimate()

    def calculateEstimatePose2(self, key: int) -> gtsam.Pose2:
        return self.isam.calculateEstimatePose2(key)

    def marginalCovariance(self, key: int) -> NDArray[np.float64]:
        """(3, 3) marginal covariance of a ``Pose2`` variable, in its tangent space."""
        return np.asarray(self.isam.marginalCovariance(key))

    def update(self, factors: gtsam.NonlinearFactorGraph | None = None, values: gtsam.Values | None = None,
               stamps: Mapping[int, float] | None = None) -> None:
        """Add ``factors`` and the new variables ``values`` (stamped by ``stamps``, s; a known key's
        stamp is moved), update iSAM2 and marginalise what is now older than the lag.  Raises
        :class:`SmootherError` if iSAM2 refuses; its state is then undefined (start a new one)."""
        for k, t in (stamps or {}).items():
            self._stamps[int(k)] = float(t)
        now = max(self._stamps.values(), default=0.0)
        marginal: list[int] = []
        if min(self._stamps.values(), default=0.0) < now - self.lag_s - self.batch_s:  # a batch is due
            marginal = sorted(k for k, t in self._stamps.items() if t < now - self.lag_s)
        up = gtsam.ISAM2UpdateParams()
        if marginal:
            # eliminate the marginal variables first (group 0), the rest after, so they end up leaves
            groups = gtsam.KeyGroupMap()
            old = set(marginal)
            for k in sorted(self._stamps):
                groups.insert2(k, 0 if k in old else 1)
            up.constrainedKeys = groups
            extra = gtsam.KeyList()
            for k in keys_to_reeliminate(BayesTree.of(self.isam), marginal):
                extra.push_back(k)
            up.extraReelimKeys = extra
        try:
            self.isam.update(factors if factors is not None else gtsam.NonlinearFactorGraph(),
                             values if values is not None else gtsam.Values(), up)
            if marginal:
                leaves = gtsam.KeyList()
                for k in marginal:
                    leaves.push_back(k)
                self.isam.marginalizeLeaves(leaves)
        except (RuntimeError, ValueError) as exc:
            raise SmootherError(str(exc)) from exc
        for k in marginal:
            del self._stamps[k]

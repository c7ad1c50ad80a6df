"""The back end's fixed-lag smoother: iSAM2 over the variables of the last ``lag_s`` seconds,
older ones marginalised. GTSAM's ``IncrementalFixedLagSmoother`` algorithm (the variables to
marginalise are ordered first, re-eliminated, then ``ISAM2.marginalizeLeaves``), with one
change: which variables are re-eliminated before a marginalisation.

Why not ``gtsam.IncrementalFixedLagSmoother`` itself: GTSAM 4.3 picks the variables to
re-eliminate (``BayesTreeMarginalizationHelper::gatherAdditionalKeysToReEliminate``) by
walking an ``std::unordered_set`` of clique *pointers*, and the set it returns depends on the
walk's order when two cliques on one path hold variables to marginalise. The order follows
the heap addresses, so two runs of the same input re-eliminated different variables and
differed by round-off from there on, which loop closures and keyframe decisions then amplify:
sequential runs of room-aggressive with ``time_offset_hold_s: 1.5`` went apart run to run
(BENCHMARKS.md, "Sequential runs deterministic with the time offset's hold"). Here every
variable of the window is re-eliminated (a batch step of iSAM2, its ordering constrained)
whenever something is marginalised: deterministic, a superset of what the helper asks for.
Cost: BENCHMARKS.md, same section.
"""

from __future__ import annotations

import gtsam


class FixedLagSmoother:
    """iSAM2 with a window of ``lag_s`` seconds (variable timestamps in seconds, any origin).

    The methods the back end uses of ``gtsam.IncrementalFixedLagSmoother``, same meaning:
    :meth:`update`, :meth:`calculateEstimate`, :meth:`getFactors`, :meth:`getISAM2Result`."""

    def __init__(self, lag_s: float, params: gtsam.ISAM2Params) -> None:
        self.lag_s = float(lag_s)
        self.isam = gtsam.ISAM2(params)
        self._stamps: dict[int, float] = {}  # variable key -> its timestamp (s)
        self._result: gtsam.ISAM2Result | None = None
        self.marginalised = 0  # variables marginalised so far

    def update(
        self,
        factors: gtsam.NonlinearFactorGraph,
        values: gtsam.Values,
        stamps: dict[int, float],
        remove: list[int] | None = None,
    ) -> None:
        """Add ``factors`` and the new variables ``values``, (re)stamp the keys of ``stamps``,
        remove the factors at ``remove``; then marginalise every variable older than the
        newest timestamp less ``lag_s``."""
        self._stamps.update(stamps)
        newest = max(self._stamps.values(), default=0.0)
        old = sorted(k for k, t in self._stamps.items() if t < newest - self.lag_s)
        constrained = extra = None
        if old:
            # old variables first in the elimination order, and the whole window re-eliminated
            # so that they all end up leaves (ISAM2.marginalizeLeaves' requirement)
            constrained = gtsam.KeyGroupMap()
            old_set = set(old)
            extra = gtsam.KeyList()
            for key in sorted(self._stamps):
                constrained.insert2(key, 0 if key in old_set else 1)
                extra.push_back(key)
        self._result = self.isam.update(
            factors, values, list(remove or []), constrained, None, extra
        )
        if old:
            leaves = gtsam.KeyList()
            for key in old:
                if self.isam.valueExists(key):
                    leaves.push_back(key)
            if leaves.size():
                self.isam.marginalizeLeaves(leaves)
                self.marginalised += leaves.size()
            for key in old:
                del self._stamps[key]
        # variables iSAM2 dropped (no factor left on them) leave the window too
        for key in [k for k in self._stamps if not self.isam.valueExists(k)]:
            del self._stamps[key]

    def calculateEstimate(self) -> gtsam.Values:  # noqa: N802 (GTSAM's name)
        return self.isam.calculateEstimate()

    def getFactors(self) -> gtsam.NonlinearFactorGraph:  # noqa: N802
        return self.isam.getFactorsUnsafe()

    def getISAM2Result(self) -> gtsam.ISAM2Result:  # noqa: N802
        if self._result is None:
            raise RuntimeError("no update yet")
        return self._result

    def timestamps(self) -> dict[int, float]:
        """Each variable's timestamp (s), the window's."""
        return dict(self._stamps)

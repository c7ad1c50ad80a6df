"""Keyframe database for place recognition: an inverted index over BoW words, and a loop
detector with normalised scores, islands and temporal consistency (DBoW2 / ORB-SLAM style).

Index layout: a compressed sparse (CSR) part sorted by word, rebuilt now and then, plus a small
list of keyframes added since (scored directly). A query gathers the index entries of its words
in one vectorised step and sums ``min(query weight, entry weight)``: the L1 score of every
keyframe sharing a word, without touching the others.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable
from dataclasses import dataclass, field

import numpy as np

from slam.loop.vocabulary import BowVector, l1_score

Exclusion = Callable[[int], bool] | set[int] | frozenset[int] | None


@dataclass(frozen=True)
class QueryResult:
    """One database hit: keyframe id, its time and the L1 score against the query."""

    kf_id: int
    t_ns: int
    score: float


def _excluded(exclude: Exclusion) -> Callable[[int], bool]:
    if exclude is None:
        return lambda _kf: False
    if callable(exclude):
        return exclude
    ids = exclude
    return lambda kf: kf in ids


class KeyframeDatabase:
    """BoW vectors of keyframes with an inverted index. Not thread-safe: one owner."""

    def __init__(self, rebuild_every: int = 64) -> None:
        self._ids: list[int] = []
        self._t_ns: list[int] = []
        self._bows: list[BowVector] = []
        self._row_of: dict[int, int] = {}
        self._rebuild_every = rebuild_every
        # CSR over rows [0, _indexed): entries sorted by word.
        self._indexed = 0
        self._words = np.zeros(0, np.int32)  # sorted unique words with entries
        self._starts = np.zeros(1, np.int64)  # entries of _words[i]: [_starts[i], _starts[i+1])
        self._entry_row = np.zeros(0, np.int32)
        self._entry_weight = np.zeros(0, np.float32)

    def __len__(self) -> int:
        return len(self._ids)

    def __contains__(self, kf_id: int) -> bool:
        return kf_id in self._row_of

    @property
    def kf_ids(self) -> list[int]:
        """Keyframe ids in insertion order."""
        return list(self._ids)

    def bow(self, kf_id: int) -> BowVector:
        return self._bows[self._row_of[kf_id]]

    def t_ns(self, kf_id: int) -> int:
        return self._t_ns[self._row_of[kf_id]]

    def row(self, kf_id: int) -> int:
        """Insertion rank of a keyframe (0 = first added)."""
        return self._row_of[kf_id]

    def add(self, kf_id: int, t_ns: int, bow: BowVector) -> None:
        """Add a keyframe's BoW vector (ids unique; insertion order = time order)."""
        if kf_id in self._row_of:
            raise ValueError(f"keyframe {kf_id} already in the database")
        self._row_of[kf_id] = len(self._ids)
        self._ids.append(int(kf_id))
        self._t_ns.append(int(t_ns))
        self._bows.append(bow)
        if len(self._ids) - self._indexed >= self._rebuild_every:
            self._rebuild()

    def _rebuild(self) -> None:
        n = len(self._bows)
        lengths = np.array([len(b) for b in self._bows], dtype=np.int64)
        words = np.concatenate([b.word_ids for b in self._bows]) if n else np.zeros(0, np.int32)
        weights = np.concatenate([b.weights for b in self._bows]) if n else np.zeros(0, np.float32)
        rows = np.repeat(np.arange(n, dtype=np.int32), lengths)
        order = np.argsort(words, kind="stable")
        words, self._entry_row, self._entry_weight = words[order], rows[order], weights[order]
        self._words, first = np.unique(words, return_index=True)
        self._starts = np.append(first, len(words)).astype(np.int64)
        self._indexed = n

    def scores(self, bow: BowVector) -> np.ndarray:
        """L1 score of ``bow`` against every keyframe, (len(self),) float64 in insertion order."""
        out = np.zeros(len(self._ids), dtype=np.float64)
        if len(bow) == 0 or not self._ids:
            return out
        if self._indexed:
            pos = np.searchsorted(self._words, bow.word_ids)
            pos_c = np.minimum(pos, len(self._words) - 1)
            hit = self._words[pos_c] == bow.word_ids
            q_weight = bow.weights[hit]
            starts = self._starts[pos_c[hit]]
            lengths = self._starts[pos_c[hit] + 1] - starts
            total = int(lengths.sum())
            if total:
                # Concatenate the entry ranges [starts[i], starts[i] + lengths[i]) in one step.
                offsets = np.repeat(starts - np.cumsum(lengths) + lengths, lengths)
                entries = offsets + np.arange(total)
                contrib = np.minimum(self._entry_weight[entries], np.repeat(q_weight, lengths))
                out[: self._indexed] = np.bincount(
                    self._entry_row[entries], weights=contrib, minlength=self._indexed
                )
        for row in range(self._indexed, len(self._ids)):
            out[row] = l1_score(bow, self._bows[row])
        return out

    def query(
        self,
        bow: BowVector,
        exclude: Exclusion = None,
        max_results: int = 10,
        min_score: float = 0.0,
    ) -> list[QueryResult]:
        """Best-scoring keyframes, highest first, skipping ``exclude`` (a set of ids or a
        predicate ``kf_id -> bool``; pass recent and covisible keyframes here)."""
        scores = self.scores(bow)
        skip = _excluded(exclude)
        order = np.argsort(-scores, kind="stable")
        out: list[QueryResult] = []
        for row in order:
            s = float(scores[row])
            if s <= min_score or s <= 0.0:
                break
            kf = self._ids[row]
            if skip(kf):
                continue
            out.append(QueryResult(kf, self._t_ns[row], s))
            if len(out) >= max_results:
                break
        return out


@dataclass(frozen=True)
class LoopDetectorParams:
    """Thresholds of place recognition (defaults follow DBoW2/ORB-SLAM practice)."""

    min_normalised_score: float = 0.3
    """Keep candidates whose score / reference score reaches this (DBoW2's alpha)."""
    min_reference_score: float = 0.005
    """Skip queries whose reference (recent neighbour) score is below this: too little texture."""
    reference_neighbours: int = 3
    """The reference score is the best score against this many most recent keyframes."""
    exclude_recent: int = 20
    """Never match the last N keyframes added before the query."""
    min_eligible: int = 20
    """No detection until this many keyframes are older than the recent ones: with a handful of
    candidates the best match is always nearby and consistency means nothing."""
    exclude_recent_ns: int = 0
    """... nor keyframes newer than t_query - this (0 = off)."""
    island_gap: int = 3
    """Candidates within this many keyframes (insertion rank) form one island."""
    min_relative_to_best: float = 0.5
    """Only hits scoring at least this fraction of the top hit form islands."""
    consistency_gap: int = 6
    """Consecutive queries are consistent when their best matches are within this many
    keyframes (insertion rank) of each other: a real revisit walks along the old path."""
    min_consecutive: int = 3
    """Accept after this many consecutive consistent queries."""
    max_candidates: int = 20


@dataclass(frozen=True)
class LoopDetection:
    """A place-recognition result to verify geometrically."""

    query_kf_id: int
    match_kf_id: int
    score: float
    normalised_score: float
    island_kf_ids: tuple[int, ...]
    consecutive: int


@dataclass
class _Island:
    first_row: int
    last_row: int
    score: float
    best_row: int
    best_score: float


@dataclass
class LoopDetector:
    """Wraps a :class:`KeyframeDatabase`: each new keyframe is queried, then added.

    Candidates are grouped into islands of neighbouring keyframes (DBoW2); the island with the
    highest summed score wins and its best keyframe is the match. Temporal consistency: the
    match of each query must lie within ``consistency_gap`` keyframes of the previous query's;
    ``min_consecutive`` such queries in a row accept.
    """

    params: LoopDetectorParams = field(default_factory=LoopDetectorParams)
    database: KeyframeDatabase = field(default_factory=KeyframeDatabase)
    _previous_island: _Island | None = None
    _consecutive: int = 0

    def process(
        self,
        kf_id: int,
        t_ns: int,
        bow: BowVector,
        exclude: Exclusion = None,
        reference_ids: Iterable[int] | None = None,
    ) -> LoopDetection | None:
        """Query with a new keyframe, then add it. ``exclude``: covisible keyframes (set or
        predicate); ``reference_ids``: neighbours for the reference score (default: the most
        recent keyframes)."""
        try:
            return self._detect(kf_id, t_ns, bow, exclude, reference_ids)
        finally:
            self.database.add(kf_id, t_ns, bow)

    def _detect(
        self,
        kf_id: int,
        t_ns: int,
        bow: BowVector,
        exclude: Exclusion,
        reference_ids: Iterable[int] | None,
    ) -> LoopDetection | None:
        p = self.params
        db = self.database
        ids = db.kf_ids
        if reference_ids is None:
            reference_ids = ids[-p.reference_neighbours :]
        refs = [l1_score(bow, db.bow(r)) for r in reference_ids if r in db]
        reference = max(refs) if refs else 0.0
        if reference < p.min_reference_score or len(ids) < p.exclude_recent + p.min_eligible:
            self._reset()
            return None
        first_recent_row = len(ids) - p.exclude_recent
        user_skip = _excluded(exclude)

        def skip(kf: int) -> bool:
            if db.row(kf) >= first_recent_row:
                return True
            if p.exclude_recent_ns and db.t_ns(kf) > t_ns - p.exclude_recent_ns:
                return True
            return user_skip(kf)

        hits = db.query(
            bow,
            exclude=skip,
            max_results=p.max_candidates,
            min_score=p.min_normalised_score * reference,
        )
        if not hits:
            self._reset()
            return None
        top = hits[0].score
        island = self._best_island(
            [(db.row(h.kf_id), h.score) for h in hits if h.score >= p.min_relative_to_best * top]
        )
        prev = self._previous_island
        if prev is not None and abs(island.best_row - prev.best_row) <= p.consistency_gap:
            self._consecutive += 1
        else:
            self._consecutive = 1
        self._previous_island = island
        if self._consecutive < p.min_consecutive:
            return None
        return LoopDetection(
            query_kf_id=kf_id,
            match_kf_id=ids[island.best_row],
            score=island.best_score,
            normalised_score=island.best_score / reference,
            island_kf_ids=tuple(
                ids[r] for r in range(island.first_row, island.last_row + 1) if not skip(ids[r])
            ),
            consecutive=self._consecutive,
        )

    def _best_island(self, rows_scores: list[tuple[int, float]]) -> _Island:
        """Group hits whose insertion ranks are within ``island_gap``; best summed score."""
        rows_scores.sort()
        islands: list[_Island] = []
        for row, score in rows_scores:
            if islands and row - islands[-1].last_row <= self.params.island_gap:
                isl = islands[-1]
                isl.last_row = row
                isl.score += score
                if score > isl.best_score:
                    isl.best_row, isl.best_score = row, score
            else:
                islands.append(_Island(row, row, score, row, score))
        return max(islands, key=lambda i: i.score)

    def _reset(self) -> None:
        self._previous_island = None
        self._consecutive = 0

"""Keyframe database (inverted index) and loop detection with temporal consistency."""

from __future__ import annotations

import numpy as np
import pytest

from slam.loop.database import KeyframeDatabase, LoopDetector, LoopDetectorParams
from slam.loop.vocabulary import BowVector, l1_score

NUM_WORDS = 50_000  # like the default vocabulary: clutter rarely shares words


def _bow(words: np.ndarray, rng: np.random.Generator) -> BowVector:
    ids, counts = np.unique(words, return_counts=True)
    w = counts * rng.uniform(0.5, 2.0, len(ids))
    return BowVector(ids.astype(np.int32), (w / w.sum()).astype(np.float32))


def _place_words(rng: np.random.Generator, n_places: int) -> list[np.ndarray]:
    return [rng.choice(NUM_WORDS, 300, replace=False) for _ in range(n_places)]


def _view(place: np.ndarray, rng: np.random.Generator, keep: float = 0.6) -> BowVector:
    """A view of a place: part of its words plus clutter."""
    seen = place[rng.random(len(place)) < keep]
    clutter = rng.choice(NUM_WORDS, 60)
    return _bow(np.concatenate([seen, clutter]), rng)


@pytest.mark.parametrize("rebuild_every", [1, 7, 1000])
def test_database_scores_equal_brute_force(rebuild_every: int) -> None:
    rng = np.random.default_rng(0)
    places = _place_words(rng, 30)
    db = KeyframeDatabase(rebuild_every=rebuild_every)
    bows = []
    for k in range(30):
        bows.append(_view(places[k], rng))
        db.add(100 + k, 1000 * k, bows[-1])
    q = _view(places[12], rng)
    expected = np.array([l1_score(q, b) for b in bows])
    np.testing.assert_allclose(db.scores(q), expected, rtol=1e-5, atol=1e-7)
    hits = db.query(q, max_results=5)
    assert hits[0].kf_id == 112
    assert [h.score for h in hits] == sorted((h.score for h in hits), reverse=True)
    assert db.query(q, exclude={112})[0].kf_id != 112
    assert all(h.kf_id % 2 for h in db.query(q, exclude=lambda kf: kf % 2 == 0))
    with pytest.raises(ValueError):
        db.add(100, 0, q)


def test_loop_detector_needs_consistent_revisit() -> None:
    rng = np.random.default_rng(1)
    n_places = 80
    places = _place_words(rng, n_places)
    # Two keyframes per place, consecutive keyframes share half their place's words.
    path = [p for p in range(n_places) for _ in range(2)]
    revisit_start = len(path)
    path += [p for p in range(10, 20) for _ in range(2)]  # come back to places 10..19
    detector = LoopDetector(LoopDetectorParams(min_consecutive=3, exclude_recent=10))
    detections = []
    for kf, place in enumerate(path):
        det = detector.process(kf, kf * 10**8, _view(places[place], rng))
        if det is not None:
            detections.append((kf, det))
    assert detections, "the revisit was not detected"
    assert all(kf >= revisit_start for kf, _ in detections)
    first_kf, first = detections[0]
    assert first_kf <= revisit_start + 6  # accepted within a few keyframes of the revisit
    assert first.consecutive >= 3
    for kf, det in detections:
        assert path[det.match_kf_id] == path[kf]  # the matched keyframe shows the same place
        assert det.normalised_score >= 0.3


def test_loop_detector_never_accepts_isolated_matches() -> None:
    """Revisits of scattered places (no two in a row) never build temporal consistency."""
    rng = np.random.default_rng(2)
    places = _place_words(rng, 120)

    def corridor_view(p: int) -> BowVector:
        # Consecutive keyframes overlap: a view shows its place and a little of the next one.
        nxt = places[(p + 1) % len(places)]
        words = np.concatenate([places[p][rng.random(300) < 0.6], nxt[rng.random(300) < 0.5]])
        return _bow(np.concatenate([words, rng.choice(NUM_WORDS, 60)]), rng)

    path = list(range(100)) + [5, 101, 40, 102, 77, 103, 20, 104, 60, 105]
    detector = LoopDetector(LoopDetectorParams(min_consecutive=3, exclude_recent=10))
    results = [detector.process(kf, kf, corridor_view(p)) for kf, p in enumerate(path)]
    assert all(r is None for r in results)

"""Benchmark of place recognition: vocabulary load, transform per image, database query.

Run: ``.venv/bin/python -m tools.bench_loop [--keyframes 1000] [--repeats 200]``

Images: the default training photographs' random variants (generated, not shared data), so the
numbers are about cost, not recognition quality. The database is filled with real BoW vectors of
such images (cycled) and queried with fresh ones.
"""

from __future__ import annotations

import argparse
import statistics
import time

import numpy as np


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--keyframes", type=int, default=1000)
    parser.add_argument("--repeats", type=int, default=200)
    parser.add_argument("--max-features", type=int, default=1000)
    args = parser.parse_args(argv)

    from slam.loop.database import KeyframeDatabase, LoopDetector
    from slam.loop.orb import detect_orb
    from slam.loop.training import AugmentOptions, default_training_images
    from slam.loop.vocabulary import default_vocabulary_path, timed_load

    load_s = []
    for _ in range(5):
        vocab, seconds = timed_load(default_vocabulary_path())
        load_s.append(seconds)
    images = list(default_training_images(AugmentOptions(variants_per_image=6, seed=7)))
    descs = [detect_orb(img, max_features=args.max_features).descriptors for img in images]
    transform_s, bows = [], []
    for d in descs:
        t0 = time.perf_counter()
        bows.append(vocab.transform(d))
        transform_s.append(time.perf_counter() - t0)
    n_desc = [len(d) for d in descs]

    db = KeyframeDatabase()
    rng = np.random.default_rng(0)
    add_s = []
    for k in range(args.keyframes):
        t0 = time.perf_counter()
        db.add(k, k * 10**8, bows[k % len(bows)])
        add_s.append(time.perf_counter() - t0)
    query_s = []
    for _ in range(args.repeats):
        q = bows[int(rng.integers(len(bows)))]
        t0 = time.perf_counter()
        db.query(q, exclude=lambda kf: kf > args.keyframes - 20, max_results=20)
        query_s.append(time.perf_counter() - t0)
    detector = LoopDetector(database=db)
    detect_s = []
    for r in range(args.repeats):
        q = bows[int(rng.integers(len(bows)))]
        t0 = time.perf_counter()
        detector.process(args.keyframes + r, (args.keyframes + r) * 10**8, q)
        detect_s.append(time.perf_counter() - t0)

    def ms(values: list[float], q: float = 0.5) -> float:
        return float(np.quantile(values, q) * 1e3)

    print(
        f"vocabulary: {vocab.num_words} words, {default_vocabulary_path().stat().st_size / 1e6:.2f} MB"
    )
    print(f"load                      median {statistics.median(load_s) * 1e3:7.1f} ms (5 runs)")
    print(
        f"transform per image       median {ms(transform_s):7.2f} ms  p95 {ms(transform_s, 0.95):6.2f} ms"
        f"  ({int(np.median(n_desc))} descriptors, {len(descs)} images)"
    )
    print(
        f"database add              median {ms(add_s):7.3f} ms  p99 {ms(add_s, 0.99):6.2f} ms (incl. index rebuilds)"
    )
    print(
        f"query, {args.keyframes} keyframes      median {ms(query_s):7.2f} ms  p95 {ms(query_s, 0.95):6.2f} ms"
        f"  (target <= 10 ms: ratio {ms(query_s) / 10:.2f})"
    )
    print(
        f"detector.process (q+add)  median {ms(detect_s):7.2f} ms  p95 {ms(detect_s, 0.95):6.2f} ms"
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

"""Benchmark: how many synthetic stereo pairs (both 752x480 images) render per second.

Builds each requested profile's sequence, renders ``--frames`` stereo pairs spread over its
duration (after one warm-up frame) and reports the median time per pair, pairs per second and
the ratio to the target (10 pairs/s), the CPU time per pair (less sensitive to other processes
on a shared machine), the time to build the scene and to render one depth image.

    .venv/bin/python -m tools.bench_render [--frames 40] [--profiles figure8 hall]
"""

from __future__ import annotations

import argparse
import os
import statistics
import time

import numpy as np

from datasets.synth.generator import make_synthetic_sequence
from datasets.synth.trajectories import PROFILES

TARGET_PAIRS_PER_S = 10.0


def bench_profile(profile: str, n_frames: int) -> dict[str, float]:
    """Median seconds per stereo pair and per depth image for one profile."""
    t0 = time.perf_counter()
    seq = make_synthetic_sequence(profile, seed=0)
    build_s = time.perf_counter() - t0
    seq.frame(0)  # warm-up (renderer set-up: pixel rays)
    indices = np.linspace(0, seq.num_frames - 1, n_frames).round().astype(int)
    pair_s = []
    cpu_s = []
    for i in indices:
        t = time.perf_counter()
        c = time.process_time()
        seq.frame(int(i))
        pair_s.append(time.perf_counter() - t)
        cpu_s.append(time.process_time() - c)
    depth_s = []
    for i in indices[:: max(1, len(indices) // 10)]:
        t = time.perf_counter()
        seq.depth(int(i))
        depth_s.append(time.perf_counter() - t)
    return {
        "build_s": build_s,
        "pair_median_s": statistics.median(pair_s),
        "pair_p90_s": float(np.quantile(pair_s, 0.9)),
        "pair_cpu_median_s": statistics.median(cpu_s),
        "depth_median_s": statistics.median(depth_s),
    }


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--frames", type=int, default=40, help="stereo pairs per profile")
    parser.add_argument("--profiles", nargs="+", default=list(PROFILES), choices=PROFILES)
    args = parser.parse_args(argv)
    print(
        f"{'profile':<11} {'build s':>8} {'pair ms':>8} {'p90 ms':>7} {'pairs/s':>8} {'x target':>9} {'depth ms':>9}"
    )
    rates = []
    for profile in args.profiles:
        r = bench_profile(profile, args.frames)
        rate = 1.0 / r["pair_median_s"]
        rates.append(rate)
        print(
            f"{profile:<11} {r['build_s']:8.2f} {1e3 * r['pair_median_s']:8.1f} "
            f"{1e3 * r['pair_p90_s']:7.1f} {rate:8.1f} {rate / TARGET_PAIRS_PER_S:9.2f} "
            f"{1e3 * r['pair_cpu_median_s']:7.1f} {1e3 * r['depth_median_s']:9.1f}"
        )
    print(
        f"load average (1 min) during the run: {os.getloadavg()[0]:.1f} on {os.cpu_count()} cores"
    )
    worst = min(rates)
    print(
        f"slowest profile: {worst:.1f} stereo pairs/s = {worst / TARGET_PAIRS_PER_S:.2f}x the "
        f"target of {TARGET_PAIRS_PER_S:.0f}/s ({'OK' if worst >= TARGET_PAIRS_PER_S else 'BELOW TARGET'})"
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

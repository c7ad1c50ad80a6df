"""Benchmark of the VIO back end on the simulated world: per-keyframe cost and accuracy.

Run: ``.venv/bin/python -m tools.bench_backend [--duration 60] [--seed 0] [--set lag_s=1.5]``

The world (``datasets.synth.vio_world``): a 10 Hz keyframe stream of ~150 tracked landmarks (0.5 px
noise, stereo) on the walls of a 12 m room, EuRoC-grade simulated IMU at 200 Hz, starting in
motion. Reports the per-keyframe ``add_keyframe`` wall time and this thread's CPU time (p50,
p99; wall time suffers from other processes on a shared machine, CPU time less so), ATE RMSE
(SE(3)-aligned) of the estimate published for each keyframe, and whether the graph stays
bounded (smoother factor count in the first vs. the second half), peak RSS (at 2 minutes of
flight and at the end: run ``--duration 1200`` for the 20-minute memory check; the simulated
world itself is held in memory, ~0.6 MB per second of flight).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import resource
import sys
import time
from typing import Any

import numpy as np
from tqdm import tqdm


def _parse_overrides(pairs: list[str]) -> dict[str, Any]:
    from slam.backend.config import BackendConfig

    fields = {f.name: f for f in dataclasses.fields(BackendConfig)}
    out: dict[str, Any] = {}
    for pair in pairs:
        key, _, value = pair.partition("=")
        if key not in fields:
            raise SystemExit(f"unknown BackendConfig field {key!r}; fields: {', '.join(fields)}")
        default = getattr(BackendConfig(), key)
        if isinstance(default, bool):
            out[key] = value.lower() in ("1", "true", "yes")
        else:
            out[key] = type(default)(value)
    return out


def run_benchmark(
    duration_s: float, seed: int, landmarks: int, overrides: dict[str, Any], progress: bool = True
) -> dict[str, Any]:
    """Run the back end over one simulated world; returns the figures as a dict."""
    from datasets.synth.vio_world import generate_world
    from slam.backend.config import BackendConfig
    from slam.backend.smoother import VioBackend
    from slam.core.messages import ImuSample
    from slam.evaluation.align import ate_se3_rmse_m

    t0 = time.perf_counter()
    world = generate_world(
        duration_s=duration_s, seed=seed, start_s=1.0, landmarks_per_keyframe=landmarks
    )
    gen_s = time.perf_counter() - t0
    rss_world_mb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
    backend = VioBackend(world.calibration, dataclasses.replace(BackendConfig(), **overrides))
    est, gt = [], []
    msgs = world.messages()
    rss_2min_mb: float | None = None
    t0 = time.perf_counter()
    for m in tqdm(msgs, desc="back end", unit="msg", disable=not progress, mininterval=1.0):
        if isinstance(m, ImuSample):
            backend.add_imu(m)
            continue
        e = backend.add_keyframe(m)
        if rss_2min_mb is None and m.t_ns - world.keyframes[0].t_ns >= 120_000_000_000:
            rss_2min_mb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
        if e is not None and e.initialized:
            est.append(e.world_from_body[:3, 3])
            gt.append(world.world_from_body_gt[m.keyframe_id][:3, 3])
    run_s = time.perf_counter() - t0
    st = backend.stats
    init_k = next(i for i, c in enumerate(st.factor_counts) if c > 0)
    wall = np.asarray(st.update_times_s[init_k + 1 :]) * 1e3
    cpu = np.asarray(st.update_cpu_s[init_k + 1 :]) * 1e3
    counts = np.asarray(st.factor_counts[init_k:])
    half = len(counts) // 2
    final = backend.estimate()
    return {
        "duration_s": duration_s,
        "seed": seed,
        "overrides": overrides,
        "keyframes": len(world.keyframes),
        "init_method": st.init_method,
        "init_after_s": (st.init_t_ns - world.keyframes[0].t_ns) * 1e-9,
        "update_wall_ms_p50": float(np.median(wall)),
        "update_wall_ms_p99": float(np.percentile(wall, 99)),
        "update_cpu_ms_p50": float(np.median(cpu)),
        "update_cpu_ms_p99": float(np.percentile(cpu, 99)),
        "ate_se3_rmse_m": ate_se3_rmse_m(np.asarray(est), np.asarray(gt)),
        "path_length_m": float(np.linalg.norm(np.diff(np.asarray(gt), axis=0), axis=1).sum()),
        "factors_max_first_half": int(counts[:half].max()),
        "factors_max_second_half": int(counts[half:].max()),
        "window_keyframes": len(final.keyframe_poses),
        "window_landmarks": len(final.landmark_ids),
        "resets": st.resets,
        "reset_reasons": list(st.failures[:5]),
        "landmarks_inserted": st.landmarks_inserted,
        "landmarks_culled": st.landmarks_culled,
        "observations_gated": st.observations_gated,
        "bias_gyro_error_rad_s": float(
            np.abs(final.bias_gyro_rad_s - world.imu.gyro_bias_rad_s[-1]).max()
        ),
        "bias_accel_error_m_s2": float(
            np.abs(final.bias_accel_m_s2 - world.imu.accel_bias_m_s2[-1]).max()
        ),
        "world_generation_s": gen_s,
        "real_time_factor": duration_s / run_s,
        "peak_rss_mb_after_world_generation": rss_world_mb,
        "peak_rss_mb_at_2min": rss_2min_mb,
        "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0,
    }


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        description=__doc__.splitlines()[0],
        epilog=__doc__.split("\n\n", 1)[1],
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("--duration", type=float, default=60.0, help="seconds of flight")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--landmarks", type=int, default=150, help="observations per keyframe")
    parser.add_argument(
        "--set", action="append", default=[], metavar="FIELD=VALUE", help="BackendConfig override"
    )
    parser.add_argument("--json", help="also write the figures to this JSON file")
    args = parser.parse_args(argv)
    res = run_benchmark(args.duration, args.seed, args.landmarks, _parse_overrides(args.set))
    for key, value in res.items():
        print(f"{key:28s} {value:.4g}" if isinstance(value, float) else f"{key:28s} {value}")
    if args.json:
        from pathlib import Path

        path = Path(args.json)
        tmp = path.with_name(path.name + ".tmp")
        tmp.write_text(json.dumps(res, indent=2))
        tmp.replace(path)
    return 0


if __name__ == "__main__":
    sys.exit(main())

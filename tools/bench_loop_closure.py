"""Benchmark of loop closure on a synthetic sequence that revisits its start.

Run: ``.venv/bin/python -m tools.bench_loop_closure [--duration 90] [--yaw-drift 0.05]``

The front end (``slam.frontend.tracker.FrontEnd``, stereo VO) runs over the ``loop`` profile;
an extra odometry drift (a yaw growing with time, like a VIO's unobservable yaw) can be injected
on top of its poses. The loop closer then sees every keyframe with that odometry; the
loop-closed trajectory maps every frame through its keyframe's correction. Reported: ATE (SE3
alignment) of the frame trajectory with and without loop closure and their ratio, accepted /
false loops (checked against ground truth), per-keyframe costs, PGO time, relocalisation time
and a database query with 1,000 keyframes.
"""

from __future__ import annotations

import argparse
import time
from typing import Any

import numpy as np


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--duration", type=float, default=90.0, help="seconds of the loop profile")
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument(
        "--yaw-drift", type=float, default=0.05, help="injected yaw drift, deg/s (0 = none)"
    )
    parser.add_argument("--aliasing", action="store_true", help="the perceptual-aliasing scene")
    args = parser.parse_args(argv)

    from tqdm import tqdm

    from datasets.synth import make_synthetic_sequence
    from datasets.synth.keyframes import Drift
    from slam.config import FrontendConfig
    from slam.core.geometry import invert_transform
    from slam.evaluation.align import ate_se3_rmse_m
    from slam.frontend.tracker import FrontEnd
    from slam.loop.closer import LoopCloser, loop_closed_poses
    from slam.loop.database import LoopDetector
    from slam.loop.relocaliser import Relocaliser

    seq = make_synthetic_sequence(
        profile="loop", duration_s=args.duration, seed=args.seed, aliasing=args.aliasing
    )
    calib = seq.calibration
    fe = FrontEnd(calib, FrontendConfig())
    closer = LoopCloser(calib)
    drift = Drift(yaw_deg_per_s=args.yaw_drift)
    t0 = int(seq.frame_times_ns()[0])
    pivot = seq.world_from_body_at(t0)[:3, 3]
    frames: list[tuple[int, int, np.ndarray]] = []
    kf_t, kf_seg, kf_ids = [], [], []
    add_ms = []
    images = {}
    for i in tqdm(range(seq.num_frames), desc="front end + loop closer", unit="frame"):
        frame = seq.frame(i)
        res, kf = fe.process(frame)
        if res.world_from_body is None:
            continue
        d = drift.at((frame.t_ns - t0) * 1e-9, pivot)
        frames.append((frame.t_ns, res.segment_id, d @ res.world_from_body))
        if i % 100 == 50:
            images[i] = frame.left
        if kf is not None:
            t1 = time.perf_counter()
            closer.add_keyframe(kf, d @ kf.world_from_body_vo)
            add_ms.append((time.perf_counter() - t1) * 1e3)
            kf_t.append(kf.t_ns)
            kf_seg.append(kf.segment_id)
            kf_ids.append(kf.keyframe_id)

    t_ns = np.array([f[0] for f in frames])
    seg = np.array([f[1] for f in frames])
    odom = np.array([f[2] for f in frames])
    truth = np.array([seq.world_from_body_at(int(t)) for t in t_ns])
    corr = closer.keyframe_map_from_odom()
    closed = loop_closed_poses(
        t_ns, seg, odom, np.array(kf_t), np.array(kf_seg), np.array([corr[k] for k in kf_ids])
    )
    ate_off = ate_se3_rmse_m(odom[:, :3, 3], truth[:, :3, 3])
    ate_on = ate_se3_rmse_m(closed[:, :3, 3], truth[:, :3, 3])
    true_kf = {k: seq.world_from_body_at(int(t)) for k, t in zip(kf_ids, kf_t, strict=True)}
    false_loops = 0
    for rec in closer.loops:
        rel = invert_transform(true_kf[rec.match_kf_id]) @ true_kf[rec.query_kf_id]
        if np.linalg.norm(rel[:3, 3] - rec.match_body_from_query_body[:3, 3]) > 0.3:
            false_loops += 1

    reloc = Relocaliser(calib, closer.store, vocabulary=closer.vocab)
    reloc_ms = []
    found = 0
    for i, img in images.items():
        r = reloc.relocalise(img, int(seq.frame_times_ns()[i]))
        reloc_ms.append(reloc.elapsed_ms[-1])
        found += r is not None

    # database query with 1,000 keyframes (the run's BoW vectors, cycled)
    bows = [closer.store.description(k).bow for k in kf_ids]
    det = LoopDetector()
    for n in range(1000):
        det.database.add(n, n * 10**8, bows[n % len(bows)])
    q_ms = []
    for n in range(200):
        t1 = time.perf_counter()
        det.process(1000 + n, (1000 + n) * 10**8, bows[(7 * n) % len(bows)])
        q_ms.append((time.perf_counter() - t1) * 1e3)

    s: dict[str, Any] = closer.stats.summary()
    print(
        f"sequence: loop profile {args.duration:.0f} s, {len(frames)} tracked frames, "
        f"{len(kf_ids)} keyframes, {len(set(kf_seg))} segment(s), injected yaw drift "
        f"{args.yaw_drift} deg/s{' (aliasing scene)' if args.aliasing else ''}"
    )
    print(f"ATE without loop closure  {ate_off:.4f} m")
    print(f"ATE with loop closure     {ate_on:.4f} m   ratio {ate_on / max(ate_off, 1e-12):.3f}")
    print(
        f"loops: detections {s['detections']}, verified {s['verified']}, accepted "
        f"{s['accepted']}, false accepted {false_loops}, rejected by gate {s['rejected_gate']}, "
        f"by PGO {s['rejected_by_pgo']}"
    )
    print(
        f"per keyframe: add median {np.median(add_ms):.1f} ms p99 {np.percentile(add_ms, 99):.1f}"
        f" ms (ORB+describe median {s['describe']['p50_ms']:.1f} ms, "
        f"BoW query {s['query']['p50_ms']:.2f} ms)"
    )
    if s["pgo_runs"]:
        print(f"PGO: {s['pgo_runs']} runs, median {s['pgo']['p50_ms']:.1f} ms")
    print(f"relocalisation: {found}/{len(images)} found, median {np.median(reloc_ms):.1f} ms")
    print(
        f"LoopDetector query+add, 1000 keyframes: median {np.median(q_ms):.2f} ms, "
        f"p95 {np.percentile(q_ms, 95):.2f} ms"
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

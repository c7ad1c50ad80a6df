"""The front end alone: per-frame time of tracking (frame in to pose out) and of the keyframe
work after it, with no other stage running.

This is the floor under the front-end latency of a whole run (``latency.frontend_frame`` in
stats.json): the same frames through :class:`slam.frontend.tracker.FrontEnd` in one thread,
nothing else on the machine's cores, no back-end estimate (constant-velocity and gyro
prediction only). Compare it with a run's ``frontend_frame_cpu`` and
``frontend_frame_runqueue`` to see what the other stages cost the front end.

    python -m tools.bench_frontend                       # room-aggressive, first 600 frames
    python -m tools.bench_frontend SEQ --frames 0 --opencv-threads 1
    python -m tools.bench_frontend --gt-prior            # a back end's estimate, from the truth

``--gt-prior`` stands in for the back end: after each keyframe the front end reads an estimate
of that keyframe made from the ground truth (pose, velocity by finite differences, zero biases),
with the keyframe's landmarks (which makes them searchable by the map reuse once untracked),
as it reads the back end's in a run. Its IMU-predicted pose is then as good as in a run, which
matters for the KLT started at the predicted projection (``frontend.klt_predicted_levels``):
without it the constant-velocity prediction fails through sharp turns and those tracks are
tracked a second time. Even with it some frames are (``frames_retracked``; none are in a run,
whose prior has the back end's biases): ``pose_cpu_not_retracked`` leaves them out.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import time
from pathlib import Path

import cv2
import numpy as np

from datasets.open import open_sequence
from slam.config import load_config
from slam.core.latency import latency_summary
from slam.core.messages import Estimate, StereoFrame
from slam.core.trajectory import Trajectory
from slam.frontend.tracker import FrontEnd
from slam.imu_buffer import ImuBuffer
from tools.benchmark import STANDARD_SUITE, default_cache_dir, ensure_sequence


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("sequence", nargs="?", help="default: the suite's room-aggressive (cached)")
    ap.add_argument("--frames", type=int, default=600, help="frames to track (0: all)")
    ap.add_argument("--config", default="euroc-stereo-imu", help="preset or YAML")
    ap.add_argument("--opencv-threads", type=int, default=0, help="0: OpenCV's default")
    ap.add_argument("--json", type=Path, help="also write the figures here")
    ap.add_argument(
        "--gt-prior", action="store_true", help="a back end's estimate at keyframes, from the truth"
    )
    args = ap.parse_args(argv)
    if args.sequence:
        path = Path(args.sequence)
    else:
        entry = next(e for e in STANDARD_SUITE if e.name == "room-aggressive")
        path = ensure_sequence(entry, default_cache_dir())
    cv2.setNumThreads(args.opencv_threads if args.opencv_threads > 0 else -1)
    seq = open_sequence(path)
    cfg = load_config(args.config)
    imu = ImuBuffer()
    frames: list[StereoFrame] = []
    for msg in seq.messages():  # IMU up to the last frame first: the player is ahead too
        if isinstance(msg, StereoFrame):
            frames.append(msg)
            if args.frames and len(frames) >= args.frames:
                break
        else:
            imu.add(msg)
    latest: list[Estimate] = []
    truth = seq.ground_truth if args.gt_prior else None
    if args.gt_prior and truth is None:
        ap.error("--gt-prior: the sequence has no ground truth")
    truth_poses = None if truth is None else truth.matrices()
    fe = FrontEnd(
        seq.calibration,
        cfg.frontend,
        imu,
        estimate_source=None if truth is None else (lambda: latest[-1] if latest else None),
    )
    pose_ms, pose_cpu_ms, after_ms, after_cpu_ms, keyframe = [], [], [], [], []
    retracked: list[bool] = []  # the frame's predicted KLT lost too many: tracked again
    for frame in frames:
        retracked_before = fe.stats.klt_retracked
        t0, c0 = time.perf_counter(), time.thread_time()
        result = fe.track(frame)
        pose_ms.append((time.perf_counter() - t0) * 1e3)
        pose_cpu_ms.append((time.thread_time() - c0) * 1e3)
        t1, c1 = time.perf_counter(), time.thread_time()
        kf = fe.after_pose()
        after_ms.append((time.perf_counter() - t1) * 1e3)
        after_cpu_ms.append((time.thread_time() - c1) * 1e3)
        if truth is not None and truth_poses is not None and kf is not None:
            est = _truth_estimate(truth, truth_poses, kf.t_ns, kf.keyframe_id)
            if fe.reframed:  # the keyframe's landmarks as the back end publishes them
                est = dataclasses.replace(
                    est,
                    landmark_ids=kf.landmark_ids,
                    landmark_positions_world=kf.points_world_vo,
                )
            latest.append(est)
        keyframe.append(result.is_keyframe)
        retracked.append(fe.stats.klt_retracked > retracked_before)
    skip = min(5, len(frames))  # the first frames start the map
    is_kf = np.array(keyframe[skip:], bool)
    after = np.array(after_ms[skip:])
    after_cpu = np.array(after_cpu_ms[skip:])
    again = np.array(retracked[skip:], bool)
    out = {
        "sequence": str(path),
        "frames": len(frames),
        "keyframes": int(is_kf.sum()),
        "opencv_threads": cv2.getNumThreads(),
        "pose": latency_summary(pose_ms[skip:]),
        "pose_cpu": latency_summary(pose_cpu_ms[skip:]),
        "pose_cpu_not_retracked": latency_summary(np.array(pose_cpu_ms[skip:])[~again].tolist()),
        "frames_retracked": int(again.sum()),
        "after_pose_on_keyframes": latency_summary(after[is_kf].tolist()),
        "after_pose_cpu_on_keyframes": latency_summary(after_cpu[is_kf].tolist()),
        "cpu_per_frame_ms": float(np.mean(pose_cpu_ms[skip:]) + np.mean(after_cpu_ms[skip:])),
        "lost_frames": fe.stats.lost_frames,
    }
    keys = ("pose", "pose_cpu", "pose_cpu_not_retracked")
    for key in (*keys, "after_pose_on_keyframes", "after_pose_cpu_on_keyframes"):
        s = out[key]
        print(
            f"{key:28s} p50 {s['p50_ms']:6.1f} ms  p90 {s['p90_ms']:6.1f}  p99 {s['p99_ms']:6.1f}"
        )
    print(f"CPU per frame (pose and after it), mean: {out['cpu_per_frame_ms']:.2f} ms")
    print(
        f"{out['frames']} frames, {out['keyframes']} keyframes, {out['lost_frames']} lost, "
        f"{out['frames_retracked']} with tracks tracked again over the full pyramid"
    )
    if args.json:
        args.json.write_text(json.dumps(out, indent=1))
    return 0


def _truth_estimate(
    truth: Trajectory, truth_poses: np.ndarray, t_ns: int, keyframe_id: int
) -> Estimate:
    """An initialised estimate of keyframe ``keyframe_id`` at ``t_ns`` from the ground truth
    (``truth_poses`` its (N, 4, 4) matrices): the nearest pose, the velocity over +-10 ms,
    zero biases."""
    i = int(np.clip(np.searchsorted(truth.t_ns, t_ns), 0, len(truth) - 1))
    lo, hi = max(i - 1, 0), min(i + 1, len(truth) - 1)
    while hi < len(truth) - 1 and truth.t_ns[hi] - truth.t_ns[lo] < 20_000_000:
        lo, hi = max(lo - 1, 0), hi + 1
    dt_s = max((truth.t_ns[hi] - truth.t_ns[lo]) * 1e-9, 1e-9)
    est = Estimate.pose_only(t_ns, keyframe_id, truth_poses[i], initialized=True)
    velocity = (truth.positions_m[hi] - truth.positions_m[lo]) / dt_s
    return dataclasses.replace(est, velocity_world_m_s=velocity)


if __name__ == "__main__":
    raise SystemExit(main())

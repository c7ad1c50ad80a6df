"""The front end alone: per-frame time of tracking (frame in to pose out) and of the keyframe
work after it, with no other stage running.

This is the floor under the front-end latency of a whole run (``latency.frontend_frame`` in
stats.json): the same frames through :class:`slam.frontend.tracker.FrontEnd` in one thread,
nothing else on the machine's cores, no back-end estimate (constant-velocity and gyro
prediction only). Compare it with a run's ``frontend_frame_cpu`` and
``frontend_frame_runqueue`` to see what the other stages cost the front end.

    python -m tools.bench_frontend                       # room-aggressive, first 600 frames
    python -m tools.bench_frontend SEQ --frames 0 --opencv-threads 1
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import cv2
import numpy as np

from datasets.open import open_sequence
from slam.config import load_config
from slam.core.latency import latency_summary
from slam.core.messages import StereoFrame
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
    fe = FrontEnd(seq.calibration, cfg.frontend, imu)
    pose_ms, pose_cpu_ms, after_ms, keyframe = [], [], [], []
    for frame in frames:
        t0, c0 = time.perf_counter(), time.thread_time()
        result = fe.track(frame)
        pose_ms.append((time.perf_counter() - t0) * 1e3)
        pose_cpu_ms.append((time.thread_time() - c0) * 1e3)
        t1 = time.perf_counter()
        fe.after_pose()
        after_ms.append((time.perf_counter() - t1) * 1e3)
        keyframe.append(result.is_keyframe)
    skip = min(5, len(frames))  # the first frames start the map
    is_kf = np.array(keyframe[skip:], bool)
    after = np.array(after_ms[skip:])
    out = {
        "sequence": str(path),
        "frames": len(frames),
        "keyframes": int(is_kf.sum()),
        "opencv_threads": cv2.getNumThreads(),
        "pose": latency_summary(pose_ms[skip:]),
        "pose_cpu": latency_summary(pose_cpu_ms[skip:]),
        "after_pose_on_keyframes": latency_summary(after[is_kf].tolist()),
        "lost_frames": fe.stats.lost_frames,
    }
    for key in ("pose", "pose_cpu", "after_pose_on_keyframes"):
        s = out[key]
        print(
            f"{key:24s} p50 {s['p50_ms']:6.1f} ms  p90 {s['p90_ms']:6.1f}  p99 {s['p99_ms']:6.1f}"
        )
    print(f"{out['frames']} frames, {out['keyframes']} keyframes, {out['lost_frames']} lost")
    if args.json:
        args.json.write_text(json.dumps(out, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

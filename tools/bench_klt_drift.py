"""Benchmark: how far tracked points drift from the surface point they started on.

On a synthetic sequence, corners are detected at several start frames (the front end's
detector), given their true 3-D point from the ground-truth depth image, and tracked for
``--seconds``; every second, each live track's pixel is compared with the projection of its
true point at the true pose. Variants: translation-only KLT frame to frame (the front end
without refinement) for each ``--windows`` size, and the same with the affine re-fit against
the birth patch every ``--period`` frames (``slam/frontend/affine_klt.py``, the default).
Reports the median and 90th percentile error (px) per age.

    .venv/bin/python -m tools.bench_klt_drift [--profile figure8] [--starts 100 300 500 700 900]

The default is the benchmark suite's room-figure8 (seed 1, 60 s).
"""

from __future__ import annotations

import argparse
from collections.abc import Sequence

import numpy as np

from datasets.synth.generator import SyntheticSequence, make_synthetic_sequence
from slam.config import FrontendConfig
from slam.frontend.affine_klt import TrackTemplates
from slam.frontend.features import detect_features, track_klt


def _true_points(seq: SyntheticSequence, frame: int, px: np.ndarray) -> np.ndarray:
    """World points (N, 3) under the pixels ``px`` (raw cam0) of ``frame``; NaN rows where
    the depth is discontinuous under the pixel."""
    intr = seq.calibration.cameras[0].intrinsics
    depth = seq.depth(frame, 0)
    u0 = np.clip(np.floor(px[:, 0]).astype(int), 0, depth.shape[1] - 2)
    v0 = np.clip(np.floor(px[:, 1]).astype(int), 0, depth.shape[0] - 2)
    a, b = px[:, 0] - u0, px[:, 1] - v0
    corners = np.stack([depth[v0, u0], depth[v0, u0 + 1], depth[v0 + 1, u0], depth[v0 + 1, u0 + 1]])
    z = corners[0] * (1 - a) * (1 - b) + corners[1] * a * (1 - b)
    z += corners[2] * (1 - a) * b + corners[3] * a * b
    z[corners.max(axis=0) - corners.min(axis=0) > 0.02 * z] = np.nan
    xy = intr.undistort_points(px.astype(float))
    cam = np.hstack([xy * z[:, None], z[:, None]])
    wfc = seq.world_from_cam(frame, 0)
    return cam @ wfc[:3, :3].T + wfc[:3, 3]


def _project(seq: SyntheticSequence, frame: int, world: np.ndarray) -> np.ndarray:
    cfw = np.linalg.inv(seq.world_from_cam(frame, 0))
    cam = world @ cfw[:3, :3].T + cfw[:3, 3]
    out = np.full((len(world), 2), np.nan)
    front = cam[:, 2] > 0.1
    out[front] = seq.calibration.cameras[0].intrinsics.project(cam[front])
    return out


def track_errors(
    seq: SyntheticSequence,
    start: int,
    n_frames: int,
    cfg: FrontendConfig,
    affine: bool,
    check_every: int,
) -> dict[int, np.ndarray]:
    """Pixel error of the live tracks every ``check_every`` frames after ``start``."""
    images = [seq.frame(start + i).left for i in range(n_frames + 1)]
    px = detect_features(images[0], np.zeros((0, 2), np.float32), cfg)
    world = _true_points(seq, start, px)
    ids = np.arange(len(px))
    templates = TrackTemplates(cfg.affine_half_window_px, cfg.affine_iterations)
    templates.add(ids, px, images[0])
    alive = np.isfinite(world).all(axis=1)
    out: dict[int, np.ndarray] = {}
    for i in range(1, n_frames + 1):
        px, ok = track_klt(images[i - 1], images[i], px, cfg)
        alive &= ok
        if affine:
            period = cfg.affine_period_frames
            turn = alive & (ids % period == i % period)
            px[turn] = templates.refine(ids[turn], px[turn], images[i])[0]
        if i % check_every == 0:
            err = np.linalg.norm(px - _project(seq, start + i, world), axis=1)
            out[i] = err[alive & np.isfinite(err)]
    return out


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--profile", default="figure8")
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--duration", type=float, default=60.0, help="sequence length (s)")
    parser.add_argument("--starts", type=int, nargs="+", default=[100, 300, 500, 700, 900])
    parser.add_argument("--seconds", type=int, default=4)
    parser.add_argument("--windows", type=int, nargs="+", default=[21, 11])
    args = parser.parse_args(argv)
    seq = make_synthetic_sequence(args.profile, duration_s=args.duration, seed=args.seed)
    fps = round(1e9 / float(np.median(np.diff(seq.frame_times_ns()))))
    n_frames = args.seconds * fps
    for window in args.windows:
        cfg = FrontendConfig(klt_window_px=window)
        for affine in (False, True):
            errors: dict[int, list[np.ndarray]] = {}
            for start in args.starts:
                for i, e in track_errors(seq, start, n_frames, cfg, affine, fps).items():
                    errors.setdefault(i, []).append(e)
            name = f"KLT {window} px" + (" + affine re-fit" if affine else "")
            cells = []
            for i in sorted(errors):
                e = np.concatenate(errors[i])
                e = e[e < 5.0]  # lost tracks (jumped to another corner) are not drift
                cells.append(
                    f"{i // fps} s: {np.median(e):.3f} / {np.percentile(e, 90):.3f} ({len(e)})"
                )
            print(f"{name:28s} median / p90 px (tracks): " + " | ".join(cells), flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

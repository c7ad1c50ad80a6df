"""Which stereo depth keeps the live mapper up at 752x480: time per keyframe and accuracy.

On a synthetic EuRoC-format room (752x480, exact depth and scene), keyframes every
``--kf-every`` frames with ground-truth poses, each method of ``DenseMapper`` computes depth
and fuses it (2 cm voxels, as ``slam run --mesh``):

- ``sweep_full`` / ``sweep_half``: plane sweep over the stereo partner and the previous keyframe
  (96 planes, at full / half size);
- ``sgbm_full`` / ``sgbm_half``: OpenCV StereoSGBM on the rectified pair (3-way mode);
- ``sgbm_full_nocheck``: without the check against the previous keyframe's depth;
- ``sgbm_full_8path``: the 5-path mode (``sgbm``).

``--only NAME...`` runs some of them.

Per method: depth + fusion ms per keyframe (median, p90; wall and CPU), the depth map's error
against the exact depth (median and p90 relative error, share of the image with depth), and the
fused mesh's accuracy (mean vertex-to-scene distance) and completion (visible scene within
5 cm) against the scene. Methods run interleaved keyframe by keyframe, so load spikes on a
shared machine hit them alike; ``--repeats`` > 1 repeats the timing and takes the median.

    .venv/bin/python -m tools.bench_mapper_depth [--profile figure8] [--duration 30] [--kf-every 10]
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import time
from dataclasses import replace
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from mapping.mapper import DenseMapper, MapperConfig
from mapping.planesweep import SweepConfig, Undistorter
from mapping.stereo_sgbm import SgbmConfig
from mapping.tsdf import TsdfConfig


def methods() -> dict[str, MapperConfig]:
    base = MapperConfig(
        tsdf=TsdfConfig(voxel_m=0.02, max_depth_m=4.0),
        sweep=SweepConfig(depth_min_m=0.4, depth_max_m=8.0, num_planes=96, threads=2),
    )
    return {
        "sweep_full": replace(base, depth_method="sweep", depth_scale=1.0),
        "sweep_half": replace(base, depth_method="sweep", depth_scale=0.5),
        "sgbm_full": replace(base, depth_method="sgbm", depth_scale=1.0),
        "sgbm_half": replace(base, depth_method="sgbm", depth_scale=0.5),
        "sgbm_full_nocheck": replace(
            base, depth_method="sgbm", depth_scale=1.0, consistency_rel_tol=0.0
        ),
        "sgbm_full_8path": replace(
            base, depth_method="sgbm", depth_scale=1.0, sgbm=SgbmConfig(mode="sgbm")
        ),
    }


def depth_errors(
    depth: np.ndarray,
    k_view: np.ndarray,
    cam0_from_view: np.ndarray,
    truth_cam0: np.ndarray,
    k_cam0: np.ndarray,
) -> np.ndarray:
    """Relative error of every valid pixel of ``depth`` (a view at ``cam0_from_view``) against
    the exact (undistorted) cam0 depth at the pixel the point projects to."""
    v, u = np.nonzero(depth > 0)
    z = depth[v, u].astype(np.float64)
    p = np.stack([(u - k_view[0, 2]) / k_view[0, 0] * z, (v - k_view[1, 2]) / k_view[1, 1] * z, z])
    q = cam0_from_view[:3, :3] @ p + cam0_from_view[:3, 3:4]
    uc = np.round(k_cam0[0, 0] * q[0] / q[2] + k_cam0[0, 2]).astype(int)
    vc = np.round(k_cam0[1, 1] * q[1] / q[2] + k_cam0[1, 2]).astype(int)
    h, w = truth_cam0.shape
    ok = (uc >= 0) & (uc < w) & (vc >= 0) & (vc < h)
    t = truth_cam0[vc[ok], uc[ok]]
    good = t > 0
    return np.abs(q[2][ok][good] - t[good]) / t[good]


def run(
    profile: str, duration_s: float, kf_every: int, seed: int, only: list[str] | None = None
) -> dict[str, Any]:
    from datasets.synth import make_synthetic_sequence
    from tools.bench_mapping import mesh_quality, visible_samples

    seq = make_synthetic_sequence(profile, duration_s=duration_s, seed=seed)
    calib = seq.calibration
    und0 = Undistorter(calib.cameras[0].intrinsics)
    cv2.setNumThreads(1)  # as the mapper worker (slam/runtime/mapper.py)
    mappers = {
        name: DenseMapper.from_calibration(calib, cfg)
        for name, cfg in methods().items()
        if not only or name in only
    }
    per: dict[str, dict[str, list[float]]] = {
        n: {"wall_ms": [], "cpu_ms": [], "err": [], "valid": []} for n in mappers
    }
    ids = list(range(0, seq.num_frames, kf_every))
    poses, truths = [], []
    for i in ids:
        frame = seq.frame(i)
        pose = seq.world_from_cam(i, 0)
        truth = und0(seq.depth(i), cv2.INTER_NEAREST)
        poses.append(pose)
        truths.append(truth)
        for name, mapper in mappers.items():
            w, c = time.perf_counter(), time.process_time()
            rep = mapper.add_keyframe(frame.t_ns, frame.left, frame.right, pose)
            wall, cpu = time.perf_counter() - w, time.process_time() - c
            if rep.skipped:
                continue
            per[name]["wall_ms"].append(1e3 * wall)
            per[name]["cpu_ms"].append(1e3 * cpu)
            kf = mapper._keyframes[frame.t_ns]  # noqa: SLF001 - a benchmark looks inside
            depth = kf.depth_m.astype(np.float32)
            per[name]["err"].extend(
                depth_errors(depth, kf.K, kf.cam0_from_view, truth, und0.K).tolist()
            )
            per[name]["valid"].append(float((depth > 0).mean()))
    samples = visible_samples(seq.scene, poses, truths, und0.K, 4.0)
    out: dict[str, Any] = {
        "sequence": f"{profile} {duration_s:.0f} s seed {seed}",
        "image": [calib.cam0.intrinsics.width, calib.cam0.intrinsics.height],
        "keyframes": len(ids),
        "keyframe_interval_ms": 1e3 * kf_every / calib.cam0.rate_hz,
        "load_average": os.getloadavg(),
    }
    for name, mapper in mappers.items():
        p = per[name]
        err = np.array(p["err"])
        out[name] = {
            "ms_per_keyframe_median": round(statistics.median(p["wall_ms"]), 1),
            "ms_per_keyframe_p90": round(float(np.quantile(p["wall_ms"], 0.9)), 1),
            "cpu_ms_per_keyframe_median": round(statistics.median(p["cpu_ms"]), 1),
            "depth_median_rel_error": round(float(np.median(err)), 4),
            "depth_p90_rel_error": round(float(np.quantile(err, 0.9)), 4),
            "depth_share_of_image": round(statistics.median(p["valid"]), 3),
            **{
                k: (round(v, 4) if isinstance(v, float) else v)
                for k, v in mesh_quality(seq.scene, mapper.mesh(), samples).items()
            },
        }
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--profile", default="figure8", help="synthetic profile (figure8)")
    ap.add_argument("--duration", type=float, default=30.0, help="seconds (30)")
    ap.add_argument("--kf-every", type=int, default=10, help="frames between keyframes (10)")
    ap.add_argument("--seed", type=int, default=1, help="sequence seed (1, as the suite)")
    ap.add_argument("--only", nargs="*", help="method names (all)")
    ap.add_argument("--json", type=Path, help="write the figures here too")
    args = ap.parse_args(argv)
    out = run(args.profile, args.duration, args.kf_every, args.seed, args.only)
    text = json.dumps(out, indent=2)
    print(text)
    if args.json:
        args.json.write_text(text + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

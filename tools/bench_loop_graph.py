"""Accuracy of a run's loop-closure pose graph against ground truth (diagnostics).

Run: ``.venv/bin/python -m tools.bench_loop_graph RUN_DIR SEQ``

``RUN_DIR`` is a ``slam run`` folder made with ``loop: {debug_graph: true}`` in its config (the
final pose graph is then in ``stats.json``); ``SEQ`` the sequence with ground truth. Reported:

* loop edges: error of the measured ``match_body_from_query_body`` against the true relative
  pose (mm, deg), next to the odometry's error over the same pair (the drift the loop must
  correct) -- a loop can only help where its error is well below the odometry's;
* odometry edges: error of consecutive keyframes' relative poses, normalised by the sigmas the
  pose graph gives them (``LoopClosureConfig.odom_sigma_*``): an RMS far from 1 means the
  weights are off;
* keyframe ATE (SE3 alignment) of the odometry and of the corrected poses.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

import numpy as np


def _mats(rows: list[list[float]]) -> np.ndarray:
    from slam.core.geometry import quat_wxyz_to_matrix

    arr = np.asarray(rows, dtype=float).reshape(-1, 7)
    out = np.tile(np.eye(4), (len(arr), 1, 1))
    out[:, :3, :3] = quat_wxyz_to_matrix(arr[:, 3:])
    out[:, :3, 3] = arr[:, :3]
    return out


def _rel_error(measured: np.ndarray, truth: np.ndarray) -> tuple[float, float]:
    """(translation error m, rotation error deg) of two relative poses."""
    from slam.core.geometry import invert_transform, rotation_angle_rad

    d = invert_transform(truth) @ measured
    return float(np.linalg.norm(d[:3, 3])), float(np.degrees(rotation_angle_rad(d[:3, :3])))


def analyse(run_dir: Path, seq_path: Path) -> dict[str, Any]:
    """The diagnostics above as a dict (see the module docstring)."""
    from datasets.open import open_sequence
    from slam.core.errors import SlamError
    from slam.core.geometry import invert_transform
    from slam.evaluation.align import ate_se3_rmse_m
    from slam.evaluation.associate import interpolate_poses
    from slam.evaluation.lie import poses_from_pq
    from slam.loop.closer import odometry_sigmas
    from slam.loop.config import LoopClosureConfig

    stats = json.loads((run_dir / "stats.json").read_text())
    graph = (stats.get("loop_closure") or {}).get("graph")
    if graph is None:
        raise SlamError(f"{run_dir}: no pose graph in stats.json (run with loop.debug_graph: true)")
    gt = open_sequence(seq_path).ground_truth
    if gt is None or len(gt) == 0:
        raise SlamError(f"{seq_path}: no ground truth")
    cfg = LoopClosureConfig()
    if (run_dir / "config.yaml").exists():  # the weights the run used
        from slam.config import load_config

        try:
            cfg = load_config(str(run_dir / "config.yaml")).loop
        except SlamError:  # a config of an older version: today's defaults
            pass
    t_ns = np.asarray(graph["t_ns"], dtype=np.int64)
    ids = [int(k) for k in graph["kf_ids"]]
    index = {k: i for i, k in enumerate(ids)}
    seg = np.asarray(graph["segment"])
    odom = _mats(graph["odometry"])
    corr = _mats(graph["corrected"])
    # The truth at each keyframe's own time, interpolated: keyframe stamps carry the online
    # time offset (room-figure8: 3.2 ms), and the next ground-truth sample (5 ms grid) instead
    # added up to 0.9 px of motion to the loop edges' errors (8.6 instead of 2.0 mm at worst).
    inside = np.clip(t_ns, gt.t_ns[0], gt.t_ns[-1])
    pos, quat = interpolate_poses(gt.t_ns, gt.positions_m, gt.q_wxyz, inside)
    true = poses_from_pq(pos, quat)
    out: dict[str, Any] = {"keyframes": len(ids), "gt_time_error_ms": 0.0}
    out["gt_time_error_ms"] = float(np.max(np.abs(inside - t_ns)) * 1e-6)

    loops = []
    for lp in graph["loops"]:
        i, j = index[int(lp["match_kf"])], index[int(lp["query_kf"])]
        truth = invert_transform(true[i]) @ true[j]
        meas = _mats([lp["match_body_from_query_body"]])[0]
        e_m, e_deg = _rel_error(meas, truth)
        o_m, o_deg = _rel_error(invert_transform(odom[i]) @ odom[j], truth)
        c_m, c_deg = _rel_error(invert_transform(corr[i]) @ corr[j], truth)
        var_m = var_rad = 0.0  # the odometry's modelled uncertainty over the loop's span
        if seg[i] == seg[j]:
            for k in range(i + 1, j + 1):
                rel = invert_transform(odom[k - 1]) @ odom[k]
                s_m, s_rad = odometry_sigmas(rel, (t_ns[k] - t_ns[k - 1]) * 1e-9, cfg)
                var_m += s_m**2
                var_rad += s_rad**2
        loops.append(
            {
                "query": ids[j],
                "match": ids[i],
                "dt_s": float((t_ns[j] - t_ns[i]) * 1e-9),
                "dist_m": float(np.linalg.norm(truth[:3, 3])),
                "inliers": lp["inliers"],
                "active": lp["active"],
                "loop_err_mm": e_m * 1e3,
                "loop_err_deg": e_deg,
                "odom_err_mm": o_m * 1e3,
                "odom_err_deg": o_deg,
                "odom_sigma_mm": float(np.sqrt(3 * var_m) * 1e3),
                "odom_sigma_deg": float(np.degrees(np.sqrt(3 * var_rad))),
                "corrected_err_mm": c_m * 1e3,
                "corrected_err_deg": c_deg,
            }
        )
    out["loops"] = loops

    norm_t, norm_r, err_t, err_r, lens = [], [], [], [], []
    for k in range(1, len(ids)):
        if seg[k] != seg[k - 1]:
            continue
        rel = invert_transform(odom[k - 1]) @ odom[k]
        truth = invert_transform(true[k - 1]) @ true[k]
        e_m, e_deg = _rel_error(rel, truth)
        length = float(np.linalg.norm(rel[:3, 3]))
        sigma_m, sigma_rad = odometry_sigmas(rel, (t_ns[k] - t_ns[k - 1]) * 1e-9, cfg)
        # per-axis sigma: a 3-D error's norm is ~sqrt(3) sigma
        norm_t.append(e_m / (sigma_m * np.sqrt(3)))
        norm_r.append(np.radians(e_deg) / (sigma_rad * np.sqrt(3)))
        err_t.append(e_m)
        err_r.append(e_deg)
        lens.append(length)
    out["odometry_edges"] = {
        "count": len(err_t),
        "length_median_m": float(np.median(lens)) if lens else None,
        "err_median_mm": float(np.median(err_t) * 1e3) if err_t else None,
        "err_rms_mm": float(np.sqrt(np.mean(np.square(err_t))) * 1e3) if err_t else None,
        "err_median_deg": float(np.median(err_r)) if err_r else None,
        "err_rms_deg": float(np.sqrt(np.mean(np.square(err_r)))) if err_r else None,
        "normalised_rms_t": float(np.sqrt(np.mean(np.square(norm_t)))) if norm_t else None,
        "normalised_rms_r": float(np.sqrt(np.mean(np.square(norm_r)))) if norm_r else None,
    }
    out["keyframe_ate_odometry_m"] = ate_se3_rmse_m(odom[:, :3, 3], true[:, :3, 3])
    out["keyframe_ate_corrected_m"] = ate_se3_rmse_m(corr[:, :3, 3], true[:, :3, 3])
    return out


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("run_dir", type=Path)
    parser.add_argument("sequence", type=Path)
    parser.add_argument("--json", action="store_true", help="print the whole result as JSON")
    args = parser.parse_args(argv)
    res = analyse(args.run_dir, args.sequence)
    if args.json:
        print(json.dumps(res, indent=2))
        return 0
    print(f"keyframes {res['keyframes']}")
    print("loop edges (error of the loop measurement | of the odometry | after PGO):")
    for lp in res["loops"]:
        print(
            f"  {lp['query']:4d} -> {lp['match']:4d}  dt {lp['dt_s']:6.1f} s  "
            f"dist {lp['dist_m']:.2f} m  inl {lp['inliers']:3d}  "
            f"loop {lp['loop_err_mm']:6.1f} mm {lp['loop_err_deg']:.2f} deg | "
            f"odom {lp['odom_err_mm']:6.1f} mm {lp['odom_err_deg']:.2f} deg "
            f"(model {lp['odom_sigma_mm']:.0f} mm {lp['odom_sigma_deg']:.2f} deg) | "
            f"pgo {lp['corrected_err_mm']:6.1f} mm {lp['corrected_err_deg']:.2f} deg"
            + ("" if lp["active"] else "  (rejected by PGO)")
        )
    o = res["odometry_edges"]
    print(
        f"odometry edges: {o['count']}, median length {o['length_median_m']:.3f} m, error "
        f"median {o['err_median_mm']:.2f} mm / {o['err_median_deg']:.3f} deg, rms "
        f"{o['err_rms_mm']:.2f} mm / {o['err_rms_deg']:.3f} deg; normalised rms "
        f"t {o['normalised_rms_t']:.3f} r {o['normalised_rms_r']:.3f} (1 = weights right)"
    )
    print(
        f"keyframe ATE: odometry {res['keyframe_ate_odometry_m']:.4f} m, corrected "
        f"{res['keyframe_ate_corrected_m']:.4f} m"
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

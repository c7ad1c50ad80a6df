"""Where is the live mapper's mesh incomplete? The mapper alone, on ground-truth poses.

Per suite sequence (cached MCAP images; ground-truth camera poses and exact depth from the
synthetic generator): a keyframe every ``--kf-every`` frames (6 = 3.3 per second, about the
front end's rate), each fused by ``DenseMapper`` exactly as configured by ``slam run --mesh``
(``MapperStageConfig`` defaults, 1 thread), with the depth range SGBM gets from the tracked
landmarks stood in for by the keyframe's exact depths (2nd and 98th percentile). No keyframe
is dropped and no pose is wrong, so what is missing is the mapper's own doing, and the
figures are deterministic (load-independent).

Scores, as ``tools.bench_live_mesh`` computes them: accuracy (mean vertex distance to the
true scene; also the median and the share beyond 5 and 10 cm), completion (share of the true
surface seen, within 4 m and unoccluded, by 60 of the keyframes, that lies within 5 cm of a
vertex), black vertices. Then the missed samples are classified: seen only beyond 2.5 / 3 m,
only near the left image border (x < 100 px, where SGBM has no disparity range), only at
grazing incidence (cos < 0.3), horizontal (floor and box tops).

``--set KEY=VALUE`` changes the mapper (``min_texture``, ``min_component``, ``min_weight``,
``max_depth_m``) for A/B runs; ``--render DIR`` writes the mesh picture (as bench_live_mesh)
and one coloured by vertex error (green 0 to red >= 10 cm).

    .venv/bin/python -m tools.bench_mesh_holes [--only room-loop] [--set min_texture=3]
"""

from __future__ import annotations

import argparse
import json
import os
import time
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np


def _mapper(calib: Any, overrides: dict[str, str]) -> Any:
    from mapping.config import MapperStageConfig
    from mapping.mapper import DenseMapper
    from slam.runtime.mapper import _make_mapper

    cfg = MapperStageConfig(enabled=True, sweep_threads=1)
    if "max_depth_m" in overrides:
        cfg = replace(cfg, max_depth_m=float(overrides["max_depth_m"]))
    mc = _make_mapper(calib, cfg).config
    if "min_texture" in overrides:
        mc = replace(mc, sgbm=replace(mc.sgbm, min_texture=float(overrides["min_texture"])))
    if "min_component" in overrides:
        mc = replace(mc, mesh_min_component_vertices=int(overrides["min_component"]))
    if "min_weight" in overrides:
        mc = replace(mc, mesh_min_weight=float(overrides["min_weight"]))
    return DenseMapper.from_calibration(calib, mc)


def missed_reasons(
    miss: np.ndarray, normals: np.ndarray, poses: list, depths: list, K: np.ndarray
) -> dict[str, float]:
    """Shares of the missed samples by why they might be missing (see the module docstring)."""
    from tools.bench_mapping import seen_in_depth

    nearest = np.full(len(miss), np.inf)
    left_only = np.ones(len(miss), bool)
    best_cos = np.zeros(len(miss))
    for pose, depth in zip(poses, depths):
        seen, z, u = seen_in_depth(miss, pose, depth, K, 4.0)
        nearest = np.where(seen, np.minimum(nearest, z), nearest)
        left_only &= ~(seen & (u >= 100))
        ray = miss - pose[:3, 3]
        ray /= np.linalg.norm(ray, axis=1, keepdims=True)
        best_cos = np.where(seen, np.maximum(best_cos, np.abs(np.sum(ray * normals, 1))), best_cos)
    if len(miss) == 0:
        return {}
    return {
        "missed_beyond_2_5m": round(float(np.mean(nearest > 2.5)), 3),
        "missed_beyond_3m": round(float(np.mean(nearest > 3.0)), 3),
        "missed_left_border_only": round(float(np.mean(left_only)), 3),
        "missed_grazing_only": round(float(np.mean(best_cos < 0.3)), 3),
        "missed_horizontal": round(float(np.mean(np.abs(normals[:, 2]) > 0.9)), 3),
    }


def run(entry: Any, kf_every: int, overrides: dict[str, str], render: Path | None) -> dict:
    import cv2
    from scipy.spatial import cKDTree

    from datasets.open import open_sequence
    from datasets.synth import make_synthetic_sequence
    from mapping.planesweep import Undistorter
    from tools.bench_mapping import distance_to_scene, visible_samples
    from tools.benchmark import default_cache_dir, ensure_sequence

    images = open_sequence(ensure_sequence(entry, default_cache_dir()))
    seq = make_synthetic_sequence(entry.profile, duration_s=entry.duration_s, seed=entry.seed)
    cv2.setNumThreads(1)
    mapper = _mapper(seq.calibration, overrides)
    mapper.volume.warm_up()
    und0 = Undistorter(seq.calibration.cameras[0].intrinsics)
    ids = list(range(0, seq.num_frames, kf_every))
    cpu_ms = []
    for i in ids:
        frame = images.frame(i)
        exact = und0(seq.depth(i), cv2.INTER_NEAREST)
        z = exact[exact > 0]
        rng = (float(np.percentile(z, 2)), float(np.percentile(z, 98))) if len(z) else None
        c = time.process_time()
        mapper.add_keyframe(
            frame.t_ns,
            frame.left,
            frame.right,
            seq.world_from_cam(i, 0),
            landmark_depth_range_m=rng,
        )
        cpu_ms.append(1e3 * (time.process_time() - c))
    mesh = mapper.mesh()
    verts = mesh.vertices_m.astype(float)
    pick = np.linspace(0, len(ids) - 1, min(60, len(ids))).round().astype(int)
    poses = [seq.world_from_cam(ids[k], 0) for k in pick]
    depths = [und0(seq.depth(ids[k]), cv2.INTER_NEAREST) for k in pick]
    samples = visible_samples(seq.scene, poses, depths, und0.K, 4.0)
    pts, normals = seq.scene.sample_surface_points(200_000, seed=1, return_normals=True)
    _, which = cKDTree(pts).query(samples)
    dist, _ = cKDTree(verts).query(samples)
    acc = distance_to_scene(seq.scene, verts)
    missed = dist >= 0.05
    out = {
        "keyframes": len(ids),
        "mapper_cpu_ms_p50": round(float(np.median(cpu_ms)), 1),
        "vertices": len(verts),
        "accuracy_mean_cm": round(100 * float(acc.mean()), 3),
        "accuracy_median_cm": round(100 * float(np.median(acc)), 3),
        "vertices_beyond_5cm": round(float(np.mean(acc > 0.05)), 4),
        "vertices_beyond_10cm": round(float(np.mean(acc > 0.10)), 4),
        "completion_5cm": round(float(np.mean(~missed)), 4),
        "black_fraction": round(float(np.mean(np.all(mesh.colors_rgb < 8, axis=1))), 4),
        **missed_reasons(samples[missed], normals[which[missed]], poses, depths, und0.K),
    }
    if render is not None:
        from datasets.ply import read_ply, write_ply_mesh
        from tools.bench_live_mesh import render_views

        render.mkdir(parents=True, exist_ok=True)
        path = render / f"{entry.name}.ply"
        write_ply_mesh(path, mesh.vertices_m, mesh.faces, mesh.normals, mesh.colors_rgb)
        ply = read_ply(path)
        render_views(verts, ply, render / f"{entry.name}.png")
        err = np.clip(acc / 0.10, 0, 1)
        ply.vertex["red"][:] = (255 * err).astype(np.uint8)
        ply.vertex["green"][:] = (255 * (1 - err)).astype(np.uint8)
        ply.vertex["blue"][:] = 0
        render_views(verts, ply, render / f"{entry.name}-error.png")
    return out


def main(argv: list[str] | None = None) -> int:
    from tools.benchmark import STANDARD_SUITE

    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--only", nargs="*", help="suite names (all)")
    ap.add_argument("--kf-every", type=int, default=6, help="frames between keyframes (6)")
    ap.add_argument("--set", nargs="*", default=[], help="KEY=VALUE mapper changes")
    ap.add_argument("--render", type=Path, help="write mesh pictures here")
    ap.add_argument("--json", type=Path, help="write the figures here too")
    args = ap.parse_args(argv)
    overrides = dict(kv.split("=", 1) for kv in args.set)
    results: dict[str, Any] = {"set": overrides, "load_average_start": os.getloadavg()}
    for entry in STANDARD_SUITE:
        if args.only and entry.name not in args.only:
            continue
        results[entry.name] = run(entry, args.kf_every, overrides, args.render)
        print(entry.name, json.dumps(results[entry.name]), flush=True)
    results["load_average_end"] = os.getloadavg()
    if args.json:
        args.json.write_text(json.dumps(results, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

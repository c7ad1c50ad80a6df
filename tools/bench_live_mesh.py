"""Does the live mapper keep up? `slam run --mesh` on the suite, with the mesh scored.

Per suite sequence (``tools.benchmark.STANDARD_SUITE``, cached MCAPs), `slam run SEQ --mesh
--speed S` in its own process, and (unless ``--no-baseline``) the same run without ``--mesh``
right after it, so the front end's p99 latency with and without the mapper is compared within
one session. From the mesh run's outputs:

- keyframes dropped by the mapper while behind (``stats.json`` mapping.dropped_fraction; those
  with a new view are fused at the end, "caught up": ``mapping.catch_up_*``), depth and
  fusion wall ms per keyframe, and the mapper process's CPU ms per keyframe (what it needs of
  a core, whatever the load);
- mesh accuracy: mean distance (m) of the vertices to the true scene, after aligning the run's
  world to the ground truth's (SE(3) Umeyama on the keyframe positions of ``keyframes.tum``);
- completion: share of the true surface that the keyframes saw (exact depth at up to
  ``--vis-keyframes`` ground-truth keyframe poses) lying within 5 cm of a vertex;
- black vertices: share with RGB all below 8 (the issue's "RGB 0,0,0", with a margin);
- a picture of the mesh in the true world frame (``SEQ-mesh/mesh.png``, see ``render_views``).

At ``--speed max`` the player does not wait for the mapper, so keyframes are dropped by
design; the mesh scores still say what the fused keyframes give. At ``--speed 1`` the drop
rate is the figure (run it on an idle machine: the mapper is a SCHED_IDLE background worker).
Ends with a Markdown table of the rows (also in ``live_mesh.md``).

    .venv/bin/python -m tools.bench_live_mesh --out /tmp/live_mesh [--speed 1] [--only hall]
    .venv/bin/python -m tools.bench_live_mesh --out /tmp/live_max --speed max --no-baseline
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
from pathlib import Path
from typing import Any

import numpy as np


def render_views(verts_gt: np.ndarray, ply: Any, path: Path) -> None:
    """A 2x2 picture of a mesh in the true world frame (z up), the upper 30 % of its height
    cut away (the ceiling would hide the room) and back faces culled (the near walls seen
    from outside): top row from above, bottom row from a high corner; left vertex colours,
    right shaded geometry."""
    import cv2

    from mapping.mesh import TriangleMesh
    from mapping.render import look_at, render_mesh

    faces = np.asarray(ply.faces, np.int64)
    normals = np.stack([ply.vertex[c] for c in ("nx", "ny", "nz")], axis=1).astype(np.float32)
    rgb = np.stack([ply.vertex[c] for c in ("red", "green", "blue")], axis=1).astype(np.uint8)
    lo, hi = np.percentile(verts_gt, 1, axis=0), np.percentile(verts_gt, 99, axis=0)
    keep = np.all(verts_gt[faces][:, :, 2] < lo[2] + 0.7 * (hi[2] - lo[2]), axis=1)
    cut = TriangleMesh(verts_gt.astype(np.float32), faces[keep], normals, rgb)
    centre = (lo + hi) / 2
    size = float(np.max(hi - lo))
    w, h = 640, 480
    k = np.array([[500.0, 0, w / 2], [0, 500.0, h / 2], [0, 0, 1]])
    top = look_at(centre + [0.0, 0.0, 1.1 * size], centre, np.array([0.0, 1.0, 0.0]))
    corner = look_at(centre + np.array([-0.8, -0.9, 0.9]) * size, centre, np.array([0, 0, 1.0]))
    rows = []
    for view in (top, corner):
        rows.append(
            np.concatenate(
                [
                    render_mesh(cut, view, k, (w, h), c, samples_per_face=6, cull_back_faces=True)
                    for c in (True, False)
                ],
                axis=1,
            )
        )
    cv2.imwrite(str(path), np.concatenate(rows, axis=0)[:, :, ::-1])


def mesh_scores(
    entry: Any, run_dir: Path, vis_keyframes: int, duration_s: float | None, render: bool = False
) -> dict[str, Any]:
    from datasets.ply import read_ply
    from datasets.synth import make_synthetic_sequence
    from mapping.planesweep import Undistorter
    from slam.evaluation.align import umeyama
    from slam.evaluation.io import read_trajectory
    from tools.bench_mapping import distance_to_scene, visible_samples

    if not (run_dir / "mesh.ply").exists():  # nothing fused
        return {"vertices": 0}
    ply = read_ply(run_dir / "mesh.ply")
    verts = np.asarray(ply.points, float)
    if len(verts) == 0:
        return {"vertices": 0}
    rgb = np.stack([ply.vertex[c] for c in ("red", "green", "blue")], axis=1)
    seq = make_synthetic_sequence(entry.profile, duration_s=duration_s, seed=entry.seed)
    est = read_trajectory(run_dir / "keyframes.tum").trajectory
    gt_body = np.array([seq.world_from_body_at(int(t)) for t in est.t_ns])
    rot, trans, _ = umeyama(est.positions_m, gt_body[:, :3, 3], with_scale=False)
    verts_gt = verts @ rot.T + trans
    times = seq.frame_times_ns()
    pick = np.linspace(0, len(est.t_ns) - 1, min(vis_keyframes, len(est.t_ns))).round()
    und0 = Undistorter(seq.calibration.cameras[0].intrinsics)
    poses, depths = [], []
    for k in pick.astype(int):
        i = int(np.clip(np.searchsorted(times, est.t_ns[k]), 0, len(times) - 1))
        poses.append(seq.world_from_cam(i, 0))
        depths.append(und0(seq.depth(i), 0))  # cv2.INTER_NEAREST
    samples = visible_samples(seq.scene, poses, depths, und0.K, 4.0)
    from scipy.spatial import cKDTree

    dist, _ = cKDTree(verts_gt).query(samples)
    acc = distance_to_scene(seq.scene, verts_gt)
    if render:
        render_views(verts_gt, ply, run_dir / "mesh.png")
    return {
        "vertices": len(verts),
        "accuracy_mean_m": round(float(acc.mean()), 4),
        "accuracy_median_m": round(float(np.median(acc)), 4),
        "completion_5cm": round(float(np.mean(dist < 0.05)), 4),
        "black_fraction": round(float(np.mean(np.all(rgb < 8, axis=1))), 4),
        "exact_black_fraction": round(float(np.mean(np.all(rgb == 0, axis=1))), 4),
    }


TABLE_COLUMNS = (
    ("sequence", None, ""),
    ("kf", "keyframes_received", "{}"),
    ("dropped", "dropped_fraction", "{:.1%}"),
    ("fused", "fused", "{}"),
    ("caught up", "caught_up", "{}"),
    ("depth ms p50", "depth_ms_p50", "{:.0f}"),
    ("fusion ms p50", "fusion_ms_p50", "{:.0f}"),
    ("mapper CPU ms/kf p50", "mapper_cpu_ms_p50", "{:.0f}"),
    ("accuracy cm", "accuracy_mean_m", "{:.2f}", 100.0),
    ("completion 5 cm", "completion_5cm", "{:.1%}"),
    ("black", "black_fraction", "{:.2%}"),
    ("FE p99 ms mesh / none", None, ""),
)


def markdown_table(results: dict[str, Any]) -> str:
    """The per-sequence rows of ``results`` as a Markdown table ("-" where a figure is
    missing)."""

    def cell(row: dict[str, Any], key: str | None, fmt: str, scale: float = 1.0) -> str:
        val = row.get(key) if key else None
        if val is None or (isinstance(val, float) and not np.isfinite(val)):
            return "-"
        return fmt.format(val * scale if scale != 1.0 else val)

    head = [c[0] for c in TABLE_COLUMNS]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for name, row in results.items():
        if not isinstance(row, dict):
            continue
        cells = [name]
        for col in TABLE_COLUMNS[1:-1]:
            cells.append(cell(row, col[1], col[2], *col[3:]))
        fe = [row.get("frontend_p99_ms_with_mesh"), row.get("frontend_p99_ms_without_mesh")]
        cells.append(" / ".join("-" if v is None else f"{v:.0f}" for v in fe))
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    from tools.benchmark import STANDARD_SUITE, default_cache_dir, ensure_sequence, run_one

    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--speed", default="1", help="slam run --speed (1)")
    ap.add_argument("--only", nargs="*", help="suite names to run (all)")
    ap.add_argument("--no-baseline", action="store_true", help="skip the run without --mesh")
    ap.add_argument("--vis-keyframes", type=int, default=60, help="keyframes for completion")
    ap.add_argument("--config", help="a config file or preset for both runs")
    ap.add_argument("--no-render", action="store_true", help="skip the mesh.png pictures")
    args = ap.parse_args(argv)
    cache = default_cache_dir()
    results: dict[str, Any] = {"speed": args.speed, "load_average_start": os.getloadavg()}
    extra = [] if not args.config else ["--config", args.config]
    for entry in STANDARD_SUITE:
        if args.only and entry.name not in args.only:
            continue
        seq_path = ensure_sequence(entry, cache)
        mesh_dir = args.out / f"{entry.name}-mesh"
        stats = run_one(seq_path, mesh_dir, None, ["--mesh", *extra], speed=args.speed)
        mp = stats.get("mapping", {})
        fe = stats.get("latency", {}).get("frontend_frame", {})
        row: dict[str, Any] = {
            "keyframes_received": mp.get("keyframes_received"),
            "dropped_fraction": round(float(mp.get("dropped_fraction", float("nan"))), 4),
            "fused": mp.get("keyframes_fused"),
            "caught_up": mp.get("keyframes_caught_up"),
            "depth_ms_p50": (mp.get("depth") or {}).get("p50_ms"),
            "fusion_ms_p50": (mp.get("fusion") or {}).get("p50_ms"),
            "mapper_cpu_ms_p50": (mp.get("cpu_per_keyframe") or {}).get("p50_ms"),
            "lag_behind_s_p90": (mp.get("lag_behind_s") or {}).get("p90_s"),
            "frontend_p99_ms_with_mesh": fe.get("p99_ms"),
            "end_of_run_s": stats.get("end_of_run_s"),
        }
        if not args.no_baseline:
            base = run_one(seq_path, args.out / f"{entry.name}-nomesh", None, extra, args.speed)
            row["frontend_p99_ms_without_mesh"] = (
                base.get("latency", {}).get("frontend_frame", {}).get("p99_ms")
            )
        row.update(
            mesh_scores(entry, mesh_dir, args.vis_keyframes, entry.duration_s, not args.no_render)
        )
        results[entry.name] = row
        print(entry.name, json.dumps(row), flush=True)
    results["load_average_end"] = os.getloadavg()
    drops = [r["dropped_fraction"] for k, r in results.items() if isinstance(r, dict)]
    if drops:
        results["dropped_fraction_median"] = statistics.median(drops)
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "live_mesh.json").write_text(json.dumps(results, indent=2) + "\n")
    table = markdown_table(results)
    (args.out / "live_mesh.md").write_text(table + "\n")
    print(json.dumps(results, indent=2))
    print(table)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

"""Benchmark of TSDF integration: real 640x480 7-Scenes depth at 1 cm voxels, ms per frame.

Our volume (``mapping.tsdf.TsdfVolume``) with each update loop that is installed (numba: the
``fast`` extra; numpy), and, when the optional ``open3d`` imports, Open3D's tensor
``VoxelBlockGrid`` and legacy ``ScalableTSDFVolume`` on the same frames as references. Each
backend integrates the same frames into a fresh volume ``--repeats`` times; the figures are the
median over passes of the per-pass median wall time per integration (all passes listed), the
median CPU time (which other processes on a shared machine disturb less), and the size of the
mesh each volume gives (an integration that fuses nothing is fast, so check it).

``--baseline-tree DIR``: also time the volume of another version of the code (before/after
within one session): each pass runs this file as a script in a child process with
``PYTHONPATH=DIR``, so ``mapping`` (and its numba loop) come from there, e.g.

    mkdir /tmp/before && git archive ed765cf mapping datasets slam | tar -x -C /tmp/before
    .venv/bin/python -m tools.bench_tsdf --baseline-tree /tmp/before

    .venv/bin/python -m tools.bench_tsdf [--frames 40] [--repeats 3] [--voxel 0.01]

The machine is usually shared: CPU time (``process_time``: all threads of this process) is
reported beside wall time, with the load average at start and end.
"""

from __future__ import annotations

import argparse
import importlib
import json
import os
import statistics
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

DATA = Path(
    os.environ.get("SLAM_DATA_DIR", Path(__file__).resolve().parents[2] / "shared" / "data")
)


def _timed_pass(
    integrate: Callable[[Any], object], frames: list, mesh_vertices: Callable[[], int]
) -> dict[str, float]:
    walls, cpus = [], []
    for fr in frames:
        w, c = time.perf_counter(), time.process_time()
        integrate(fr)
        walls.append(time.perf_counter() - w)
        cpus.append(time.process_time() - c)
    return {
        "ms": 1e3 * statistics.median(walls),
        "cpu_ms": 1e3 * statistics.median(cpus),
        "mesh_vertices": mesh_vertices(),
    }


def _ours(
    kernel: str, frames: list, K: np.ndarray, voxel_m: float, threads: int = 1
) -> dict[str, float]:
    from mapping.mesh import extract_mesh
    from mapping.tsdf import TsdfConfig, TsdfVolume

    cfg = TsdfConfig(
        voxel_m=voxel_m, truncation_m=4 * voxel_m, max_depth_m=4.0, kernel=kernel, threads=threads
    )
    vol = TsdfVolume(cfg)
    vol.integrate(frames[0].depth_m, K, frames[0].world_from_cam, frames[0].color_rgb)  # JIT
    vol = TsdfVolume(cfg)
    return _timed_pass(
        lambda fr: vol.integrate(fr.depth_m, K, fr.world_from_cam, fr.color_rgb),
        frames,
        lambda: extract_mesh(vol).num_vertices,
    )


def _baseline_tree(
    tree: Path, kernel: str, n_frames: int, voxel_m: float, threads: int = 1
) -> dict[str, float]:
    """One pass of ``_ours`` with the code under ``tree`` (a child process; see the module
    docstring)."""
    env = dict(os.environ, PYTHONPATH=str(tree))
    cmd = [sys.executable, str(Path(__file__).resolve()), "--one", kernel, "--threads"]
    cmd += [str(threads), "--frames", str(n_frames), "--voxel", str(voxel_m)]
    proc = subprocess.run(cmd, capture_output=True, text=True, env=env, check=False)
    if proc.returncode != 0:
        raise RuntimeError(f"baseline pass failed: {proc.stderr.strip()[-500:]}")
    return json.loads(proc.stdout.strip().splitlines()[-1])


def _frames(n_frames: int) -> tuple[list, np.ndarray]:
    from datasets.rgbd_folder import RgbdFolder

    folder = RgbdFolder(DATA / "7scenes_rgbd_400")
    ids = np.linspace(0, len(folder) - 1, n_frames).round().astype(int)
    return [folder.frame(int(i)) for i in ids], folder.K


def _open3d_tensor(o3d: Any, frames: list, K: np.ndarray, voxel_m: float) -> dict[str, float]:
    o3c = o3d.core
    vbg = o3d.t.geometry.VoxelBlockGrid(
        attr_names=("tsdf", "weight", "color"),
        attr_dtypes=(o3c.float32, o3c.float32, o3c.float32),
        attr_channels=((1), (1), (3)),
        voxel_size=voxel_m,
        block_resolution=8,
        block_count=50000,
        device=o3c.Device("CPU:0"),
    )
    k = o3c.Tensor(K, o3c.float64)

    def integrate(fr: Any) -> None:
        depth = o3d.t.geometry.Image(o3c.Tensor(np.ascontiguousarray(fr.depth_m)))
        color = o3d.t.geometry.Image(o3c.Tensor(fr.color_rgb.astype(np.float32)))
        ext = o3c.Tensor(np.linalg.inv(fr.world_from_cam), o3c.float64)  # cam_from_world
        coords = vbg.compute_unique_block_coordinates(depth, k, ext, 1.0, 4.0)
        vbg.integrate(coords, depth, color, k, k, ext, 1.0, 4.0, 4.0)

    return _timed_pass(
        integrate, frames, lambda: int(vbg.extract_triangle_mesh().vertex.positions.shape[0])
    )


def _open3d_scalable(o3d: Any, frames: list, K: np.ndarray, voxel_m: float) -> dict[str, float]:
    h, w = frames[0].depth_m.shape
    intr = o3d.camera.PinholeCameraIntrinsic(w, h, K[0, 0], K[1, 1], K[0, 2], K[1, 2])
    vol = o3d.pipelines.integration.ScalableTSDFVolume(
        voxel_length=voxel_m,
        sdf_trunc=4 * voxel_m,
        color_type=o3d.pipelines.integration.TSDFVolumeColorType.RGB8,
    )

    def integrate(fr: Any) -> None:
        rgbd = o3d.geometry.RGBDImage.create_from_color_and_depth(
            o3d.geometry.Image(np.ascontiguousarray(fr.color_rgb)),
            o3d.geometry.Image(np.round(fr.depth_m * 1000).astype(np.uint16)),
            depth_scale=1000.0,
            depth_trunc=4.0,
            convert_rgb_to_intensity=False,
        )
        vol.integrate(rgbd, intr, np.linalg.inv(fr.world_from_cam))

    return _timed_pass(integrate, frames, lambda: len(vol.extract_triangle_mesh().vertices))


def run(
    n_frames: int, repeats: int, voxel_m: float, baseline_tree: Path | None = None
) -> dict[str, Any]:
    from mapping.tsdf import numba_available

    frames, K = _frames(n_frames)
    backends: dict[str, Callable[[], dict[str, float]]] = {}
    if numba_available():
        backends["ours_numba"] = lambda: _ours("numba", frames, K, voxel_m)
        backends["ours_numba_2threads"] = lambda: _ours("numba", frames, K, voxel_m, 2)
        if baseline_tree is not None:
            backends["baseline_numba"] = lambda: _baseline_tree(
                baseline_tree, "numba", n_frames, voxel_m
            )
    backends["ours_numpy"] = lambda: _ours("numpy", frames, K, voxel_m)
    if baseline_tree is not None:
        backends["baseline_numpy"] = lambda: _baseline_tree(
            baseline_tree, "numpy", n_frames, voxel_m
        )
    try:
        o3d: Any = importlib.import_module("open3d")  # optional: the `mesh` extra
    except ImportError:
        o3d = None
    if o3d is not None:
        backends["open3d_voxelblockgrid"] = lambda: _open3d_tensor(o3d, frames, K, voxel_m)
        backends["open3d_scalable"] = lambda: _open3d_scalable(o3d, frames, K, voxel_m)
    out: dict[str, Any] = {
        "frames": len(frames),
        "image": [int(frames[0].depth_m.shape[1]), int(frames[0].depth_m.shape[0])],
        "voxel_m": voxel_m,
        "repeats": repeats,
        "open3d": "not installed" if o3d is None else o3d.__version__,
        "load_average_start": os.getloadavg(),
    }
    passes: dict[str, list[dict[str, float]]] = {name: [] for name in backends}
    for _ in range(repeats):  # interleaved, so a busy spell hits every backend alike
        for name, fn in backends.items():
            passes[name].append(fn())
    out["load_average_end"] = os.getloadavg()
    for name, ps in passes.items():
        out[name] = {
            "ms_median": round(statistics.median(p["ms"] for p in ps), 2),
            "ms_each_pass": [round(p["ms"], 2) for p in ps],
            "cpu_ms_median": round(statistics.median(p["cpu_ms"] for p in ps), 2),
            "mesh_vertices": int(ps[-1]["mesh_vertices"]),
        }
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--frames", type=int, default=40, help="frames spread over the 400 (40)")
    ap.add_argument("--repeats", type=int, default=3, help="passes; median of them (3)")
    ap.add_argument("--voxel", type=float, default=0.01, help="voxel size, m (0.01)")
    ap.add_argument("--baseline-tree", type=Path, help="a source tree of the code before")
    ap.add_argument("--json", type=Path, help="write the figures here too")
    ap.add_argument("--one", choices=("numba", "numpy"), help=argparse.SUPPRESS)  # child pass
    ap.add_argument("--threads", type=int, default=1, help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.one:
        frames, K = _frames(args.frames)
        print(json.dumps(_ours(args.one, frames, K, args.voxel, args.threads)))
        return 0
    out = run(args.frames, args.repeats, args.voxel, args.baseline_tree)
    text = json.dumps(out, indent=2)
    print(text)
    if args.json:
        args.json.write_text(text + "\n")
    return 0


if __name__ == "__main__":
    if __package__ in (None, ""):  # run as a script (a baseline pass): the tree's packages
        sys.path[:0] = [p for p in os.environ.get("PYTHONPATH", "").split(os.pathsep) if p]
    raise SystemExit(main())

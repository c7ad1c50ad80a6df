"""Offline fusion: an RGB-D folder (sensor depth) or a camera sequence + trajectory (plane sweep)
into one TSDF mesh. The library side of ``slam fuse``."""

from __future__ import annotations

import hashlib
import json
import logging
import os
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
from tqdm import tqdm

from mapping.mapper import DenseMapper, MapperConfig
from mapping.mesh import TriangleMesh
from slam.core.errors import InputError
from slam.core.trajectory import Trajectory

if TYPE_CHECKING:
    from datasets.rgbd_calibration import ColorCalibration, ColorCalibrationConfig
    from datasets.rgbd_folder import RgbdFolder

log = logging.getLogger(__name__)

COLOR_CALIBRATION_VERSION = 1
"""Bumped when the calibration (or its cache file) changes meaning; old caches are redone."""


@dataclass
class FuseResult:
    """A fused mesh and how it was made."""

    mesh: TriangleMesh
    mapper: DenseMapper
    frames_used: int
    source: str
    depth_ms: list[float] = field(default_factory=list)
    fusion_ms: list[float] = field(default_factory=list)
    mesh_s: float = 0.0
    color_registered: bool = False
    """RGB-D: the colour was registered to the depth (``color_registration``) before fusion."""
    color_error: float | None = None
    """RGB-D: mean absolute difference (grey levels, RGB mean) between the mesh's vertex colours
    and the registered colour images where vertices are seen (``mesh_color_error``)."""

    def summary(self) -> str:
        lo, hi = self.mesh.bounds() if self.mesh.num_vertices else (np.zeros(3), np.zeros(3))
        med = lambda x: float(np.median(x)) if x else 0.0  # noqa: E731
        return (
            f"{self.frames_used} frames ({self.source}): {self.mesh.num_vertices} vertices, "
            f"{self.mesh.num_faces} faces, bounds {np.round(lo.astype(float), 2).tolist()} .. "
            f"{np.round(hi.astype(float), 2).tolist()} m; median depth {med(self.depth_ms):.0f} ms, "
            f"fusion {med(self.fusion_ms):.0f} ms per frame, meshing {self.mesh_s:.1f} s"
            + (
                ""
                if self.color_error is None
                else f"; colour {'registered' if self.color_registered else 'NOT registered'}"
                f", mesh colour error {self.color_error:.1f} grey levels against the registered"
                " colour images"
            )
        )


def default_cache_dir() -> Path:
    """``$XDG_CACHE_HOME/pyvislam`` (``~/.cache/pyvislam``)."""
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(base) / "pyvislam"


def _folder_key(folder: RgbdFolder) -> str:
    """What identifies a folder's frames: its resolved path, frame count and the first and last
    depth files' sizes and times (a changed folder gets a new calibration)."""
    files = [folder.root / f"frame-{folder.frame_ids[i]:06d}.depth.png" for i in (0, -1)]
    parts = [str(folder.root.resolve()), str(len(folder))]
    parts += [f"{f.stat().st_size}:{f.stat().st_mtime_ns}" for f in files]
    return hashlib.sha1("|".join(parts).encode()).hexdigest()[:16]


def focal_only_calibration() -> ColorCalibrationConfig:
    """What the frames of a 7-Scenes-like folder determine: one focal length (principal point
    at the centre, the colour camera at the depth camera, no distortion, no time offset).
    Freeing more let the extrinsic move by 2-3 cm between calibration subsets on 7-Scenes
    (``datasets/rgbd_calibration.py``, ``tests/test_mapping_planesweep.py``); the focal length
    was reproducible (524-529 px) and is most of the registration (depth camera: 585 px)."""
    from datasets.rgbd_calibration import ColorCalibrationConfig

    return ColorCalibrationConfig(
        separate_focals=False,
        distortion=False,
        time_offset=False,
        fixed=("cx", "cy", "rx", "ry", "rz", "tx", "ty", "tz"),
        max_corners=300,
        outer_iterations=3,
    )


def color_registration(
    folder: RgbdFolder,
    cache_dir: Path | None = None,
    progress: bool = True,
    config: ColorCalibrationConfig | None = None,
) -> ColorCalibration:
    """The colour camera of an RGB-D folder (``datasets.rgbd_calibration``; ``config`` default
    :func:`focal_only_calibration`), computed once per folder and configuration (pairs 10
    frames apart from 16 starts spread over the folder) and cached as JSON in ``cache_dir``
    (default ``default_cache_dir()/rgbd_calibration``: shared data folders are often
    read-only)."""
    from datasets.rgbd_calibration import (
        ColorCalibration,
        calibrate_color_camera,
        calibration_pairs,
    )
    from slam.core.atomic import write_atomic
    from slam.core.calibration import CameraIntrinsics

    config = config or focal_only_calibration()
    cfg_key = hashlib.sha1(repr(config).encode()).hexdigest()[:8]
    cache = (cache_dir or default_cache_dir() / "rgbd_calibration") / (
        f"{folder.root.name}-{_folder_key(folder)}-{cfg_key}-v{COLOR_CALIBRATION_VERSION}.json"
    )
    if cache.exists():
        try:
            d = json.loads(cache.read_text())
            return ColorCalibration(
                intrinsics=CameraIntrinsics.from_dict(d["intrinsics"]),
                color_from_depth=np.array(d["color_from_depth"], float),
                time_offset_frames=float(d["time_offset_frames"]),
                rms_px=float(d["rms_px"]),
                median_px=float(d["median_px"]),
                num_points=int(d["num_points"]),
            )
        except (OSError, ValueError, KeyError) as exc:
            log.warning("%s: unreadable colour calibration cache (%s); recomputing", cache, exc)
    gap = 10
    starts = np.linspace(0, max(len(folder) - 1 - gap, 0), 16).round().astype(int)
    frames = sorted({int(i) for i in starts} | {int(i) + gap for i in starts})
    frames = [i for i in frames if i < len(folder)]
    log.info("calibrating the colour camera of %s (cached in %s)", folder.root, cache)
    cal = calibrate_color_camera(folder, calibration_pairs(frames, gap), config, progress)
    cache.parent.mkdir(parents=True, exist_ok=True)
    record = {
        "folder": str(folder.root.resolve()),
        "intrinsics": cal.intrinsics.to_dict(),
        "color_from_depth": cal.color_from_depth.tolist(),
        "time_offset_frames": cal.time_offset_frames,
        "rms_px": cal.rms_px,
        "median_px": cal.median_px,
        "num_points": cal.num_points,
    }
    write_atomic(cache, json.dumps(record, indent=1) + "\n")
    return cal


def registered_color(
    folder: RgbdFolder, cal: ColorCalibration, poses: object, i: int, depth_m: np.ndarray
) -> np.ndarray:
    """Frame ``i``'s colour resampled onto its depth pixels (0 where no depth)."""
    from datasets.rgbd_calibration import color_in_depth_camera

    color_from_depth = cal.color_from_depth_frame(poses, i, i)  # type: ignore[arg-type]
    return color_in_depth_camera(
        folder.color_rgb(i), depth_m, folder.K, cal.intrinsics, color_from_depth
    )


def mesh_color_error(
    mesh: TriangleMesh,
    folder: RgbdFolder,
    cal: ColorCalibration,
    frames: list[int],
    max_depth_gap_m: float = 0.02,
) -> float:
    """Mean absolute difference (grey levels, mean over R, G, B) between vertex colours and the
    registered colour images of ``frames``, over the vertices each frame sees: projected into
    its depth camera with its pose, within ``max_depth_gap_m`` of the sensor depth there."""
    from datasets.rgbd_calibration import PoseInterpolator

    if mesh.colors_rgb is None or mesh.num_vertices == 0:
        return float("nan")
    poses = PoseInterpolator(folder)
    verts = mesh.vertices_m.astype(np.float64)
    cols = mesh.colors_rgb.astype(np.float64)
    total, count = 0.0, 0
    K = folder.K
    for i in frames:
        depth = folder.depth_m(i)
        reg = registered_color(folder, cal, poses, i, depth)
        cam_from_world = np.linalg.inv(folder.pose(i))
        pc = verts @ cam_from_world[:3, :3].T + cam_from_world[:3, 3]
        z = pc[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            u = np.round(K[0, 0] * pc[:, 0] / z + K[0, 2])
            v = np.round(K[1, 1] * pc[:, 1] / z + K[1, 2])
        h, w = depth.shape
        ok = (z > 0.1) & (u >= 0) & (u < w) & (v >= 0) & (v < h)
        ui, vi = u[ok].astype(int), v[ok].astype(int)
        seen = (np.abs(depth[vi, ui] - z[ok]) < max_depth_gap_m) & np.any(reg[vi, ui] > 0, axis=1)
        diff = np.abs(cols[ok][seen] - reg[vi[seen], ui[seen]].astype(np.float64)).mean(axis=1)
        total += float(diff.sum())
        count += len(diff)
    return total / max(count, 1)


def poses_at(trajectory: Trajectory, t_ns: np.ndarray, max_gap_ns: int) -> np.ndarray:
    """world_from_body (N, 4, 4) at ``t_ns`` by linear/SLERP interpolation; NaN where ``t_ns``
    lies outside the trajectory or its bracketing samples are more than ``max_gap_ns`` apart."""
    from scipy.spatial.transform import Rotation, Slerp

    t_ref = trajectory.t_ns
    out = np.full((len(t_ns), 4, 4), np.nan)
    if len(t_ref) < 2:
        return out
    idx = np.clip(np.searchsorted(t_ref, t_ns), 1, len(t_ref) - 1)
    ok = (t_ns >= t_ref[0]) & (t_ns <= t_ref[-1]) & (t_ref[idx] - t_ref[idx - 1] <= max_gap_ns)
    if not ok.any():
        return out
    rots = Rotation.from_quat(trajectory.q_wxyz[:, [1, 2, 3, 0]])  # scipy wants x,y,z,w
    slerp = Slerp(t_ref.astype(np.float64), rots)
    tq = t_ns[ok]
    i = idx[ok]
    frac = ((tq - t_ref[i - 1]) / (t_ref[i] - t_ref[i - 1])).astype(np.float64)
    pos = trajectory.positions_m[i - 1] + frac[:, None] * (
        trajectory.positions_m[i] - trajectory.positions_m[i - 1]
    )
    sel = np.zeros((ok.sum(), 4, 4))
    sel[:, :3, :3] = slerp(tq.astype(np.float64)).as_matrix()
    sel[:, :3, 3] = pos
    sel[:, 3, 3] = 1.0
    out[ok] = sel
    return out


def fuse_rgbd_folder(
    path: str | Path,
    config: MapperConfig,
    every: int = 1,
    max_frames: int | None = None,
    trajectory: Trajectory | None = None,
    progress: bool = True,
    register_color: bool = True,
    color_error_frames: int = 20,
    calibration_cache: Path | None = None,
    color_calibration: ColorCalibration | None = None,
) -> FuseResult:
    """Fuse the sensor depth of a 7-Scenes-layout folder with its per-frame poses (or with
    ``trajectory``, world_from_camera, matched by the folder's synthesised 30 Hz times).

    ``register_color``: resample each colour image onto its depth pixels with the folder's
    colour calibration (:func:`color_registration`, cached) before fusing (else the colour
    image is used as if taken by the depth camera). ``color_error_frames`` > 0 (and the folder
    has poses): report the mesh's colour error against that many registered colour images
    (:func:`mesh_color_error`), registered or not. ``color_calibration``: use this one instead
    of :func:`color_registration`'s.
    """
    from datasets.rgbd_calibration import PoseInterpolator
    from datasets.rgbd_folder import RgbdFolder

    folder = RgbdFolder(path)
    want_cal = (register_color or color_error_frames > 0) and folder.has_poses()
    cal = color_calibration
    if cal is None and want_cal:
        cal = color_registration(folder, calibration_cache, progress)
    pose_interp = PoseInterpolator(folder) if cal is not None else None
    if trajectory is None and not folder.has_poses():
        raise InputError(f"{path}: no frame-*.pose.txt files; pass --trajectory FILE")
    ids = list(range(0, len(folder), max(1, every)))
    if max_frames is not None:
        ids = ids[:max_frames]
    poses = None
    if trajectory is not None:
        poses = poses_at(trajectory, np.array([folder.t_ns(i) for i in ids]), 10**9)
    mapper = DenseMapper(config)
    result = FuseResult(TriangleMesh.empty(), mapper, 0, "sensor depth")
    result.color_registered = register_color and cal is not None
    for n, i in enumerate(tqdm(ids, desc="fuse", unit="frame", disable=not progress)):
        pose = folder.pose(i) if poses is None else poses[n]
        if not np.all(np.isfinite(pose)):
            continue
        depth = folder.depth_m(i)
        if result.color_registered:
            assert cal is not None
            color = registered_color(folder, cal, pose_interp, i, depth)
        else:
            color = folder.color_rgb(i)
        rep = mapper.add_keyframe(folder.t_ns(i), color, None, pose, K=folder.K, depth_m=depth)
        result.fusion_ms.append(rep.fusion_ms)
        result.frames_used += 1
    if result.frames_used == 0:
        raise InputError(f"{path}: no frame had a pose; check the trajectory's time range")
    t0 = time.perf_counter()
    result.mesh = mapper.mesh()
    result.mesh_s = time.perf_counter() - t0
    if cal is not None and color_error_frames > 0:
        picks = np.linspace(0, len(ids) - 1, min(color_error_frames, len(ids))).round()
        check = [ids[int(k)] + (_half_step(ids)) for k in picks]
        check = [min(c, len(folder) - 1) for c in check]
        result.color_error = mesh_color_error(result.mesh, folder, cal, check)
    return result


def _half_step(ids: list[int]) -> int:
    """Half the frame step: the colour error is checked on frames between the fused ones
    where there are any (not the very images that were fused)."""
    return (ids[1] - ids[0]) // 2 if len(ids) > 1 else 0


def fuse_sequence(
    sequence_path: str | Path,
    trajectory: Trajectory | None,
    config: MapperConfig,
    every: int = 10,
    max_frames: int | None = None,
    progress: bool = True,
) -> FuseResult:
    """Plane sweep every ``every``-th frame of a camera sequence posed by ``trajectory``
    (world_from_body; the sequence's ground truth when None), then fuse."""
    from datasets.open import open_sequence

    seq = open_sequence(sequence_path)
    source = "plane sweep"
    if trajectory is None:
        if seq.ground_truth is None:
            raise InputError(
                f"{sequence_path}: the sequence has no ground truth; pass --trajectory FILE"
            )
        trajectory = seq.ground_truth
        source += " on ground-truth poses"
        log.info("no --trajectory: using the sequence's ground truth")
    times = seq.image_times_ns()  # the middle of each exposure, as `slam run` stamps
    ids = np.arange(0, len(times), max(1, every))
    if max_frames is not None:
        ids = ids[:max_frames]
    body_from_cam0 = seq.calibration.cam0.body_from_cam
    poses = poses_at(trajectory, times[ids], max_gap_ns=int(0.5e9))
    mapper = DenseMapper.from_calibration(seq.calibration, config)
    result = FuseResult(TriangleMesh.empty(), mapper, 0, source)
    for n, i in enumerate(tqdm(ids, desc="sweep+fuse", unit="kf", disable=not progress)):
        if not np.all(np.isfinite(poses[n])):
            continue
        frame = seq.frame(int(i))
        rep = mapper.add_keyframe(int(times[i]), frame.left, frame.right, poses[n] @ body_from_cam0)
        result.depth_ms.append(rep.depth_ms)
        result.fusion_ms.append(rep.fusion_ms)
        result.frames_used += 1
    if result.frames_used == 0:
        raise InputError(
            f"{sequence_path}: no frame time lies inside the trajectory; check the file's clock"
        )
    t0 = time.perf_counter()
    result.mesh = mapper.mesh()
    result.mesh_s = time.perf_counter() - t0
    return result

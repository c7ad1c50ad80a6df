"""Offline fusion: an RGB-D folder (sensor depth) or a camera sequence + trajectory (plane sweep)
into one TSDF mesh. The library side of ``slam fuse``."""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from tqdm import tqdm

from mapping.mapper import DenseMapper, MapperConfig
from mapping.mesh import TriangleMesh
from slam.core.errors import InputError
from slam.core.trajectory import Trajectory

log = logging.getLogger(__name__)


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

    def summary(self) -> str:
        lo, hi = self.mesh.bounds() if self.mesh.num_vertices else (np.zeros(3), np.zeros(3))
        med = lambda x: float(np.median(x)) if x else 0.0  # noqa: E731
        return (
            f"{self.frames_used} frames ({self.source}): {self.mesh.num_vertices} vertices, "
            f"{self.mesh.num_faces} faces, bounds {np.round(lo.astype(float), 2).tolist()} .. "
            f"{np.round(hi.astype(float), 2).tolist()} m; median depth {med(self.depth_ms):.0f} ms, "
            f"fusion {med(self.fusion_ms):.0f} ms per frame, meshing {self.mesh_s:.1f} s"
        )


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
) -> FuseResult:
    """Fuse the sensor depth of a 7-Scenes-layout folder with its per-frame poses (or with
    ``trajectory``, world_from_camera, matched by the folder's synthesised 30 Hz times)."""
    from datasets.rgbd_folder import RgbdFolder

    folder = RgbdFolder(path)
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
    for n, i in enumerate(tqdm(ids, desc="fuse", unit="frame", disable=not progress)):
        pose = folder.pose(i) if poses is None else poses[n]
        if not np.all(np.isfinite(pose)):
            continue
        rep = mapper.add_keyframe(
            folder.t_ns(i),
            folder.color_rgb(i),
            None,
            pose,
            K=folder.K,
            depth_m=folder.depth_m(i),
        )
        result.fusion_ms.append(rep.fusion_ms)
        result.frames_used += 1
    if result.frames_used == 0:
        raise InputError(f"{path}: no frame had a pose; check the trajectory's time range")
    t0 = time.perf_counter()
    result.mesh = mapper.mesh()
    result.mesh_s = time.perf_counter() - t0
    return result


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
    times = seq.frame_times_ns()
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
        rep = mapper.add_keyframe(
            int(frame.t_ns), frame.left, frame.right, poses[n] @ body_from_cam0
        )
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

"""Write a synthetic sequence's extras: ground-truth depth images and the scene mesh (PLY).

The MCAP itself is written by :func:`datasets.mcap_io.write_sequence_mcap`; this module adds
what only the generator knows. All outputs are written atomically (temp file + os.replace).
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
from tqdm import tqdm

from datasets.ply import write_ply_mesh
from datasets.synth.camera_model import CameraEffects
from datasets.synth.generator import SyntheticSequence
from datasets.synth.imu_check import AccelScale, GyroAgreement
from datasets.synth.imu_sim import ImuEffects
from slam.core.atomic import write_atomic
from slam.core.errors import InputError

DEPTH_SCALE_M = 0.001  # one unit of the 16-bit depth PNGs, metres (TUM/7-Scenes convention)
DEPTH_NAME_DIGITS = 19  # EuRoC's zero-padded nanoseconds: names sort in time order


def depth_image_name(t_ns: int) -> str:
    """``<t_ns>.png`` with ``t_ns`` zero-padded to 19 digits (as EuRoC names images), so that
    the names sort in time order."""
    return f"{int(t_ns):0{DEPTH_NAME_DIGITS}d}.png"


def read_depth_folder(path: str | os.PathLike[str]) -> tuple[np.ndarray, list[Path]]:
    """The depth images of a :func:`write_depth_images` folder: (t_ns int64, paths), in time
    order. Reads zero-padded names and the unpadded ones of older versions alike."""
    root = Path(path)
    if not (root / "depth.json").is_file():
        raise InputError(
            f"{root}: no depth.json; give a folder written by `slam synth --depth-dir`"
        )
    found = sorted((int(p.stem), p) for p in root.glob("*.png") if p.stem.isdigit() and p.is_file())
    return np.array([t for t, _ in found], dtype=np.int64), [p for _, p in found]


def write_depth_images(
    seq: SyntheticSequence, out_dir: str | os.PathLike[str], cam: int = 0, progress: bool = True
) -> int:
    """Ground-truth depth of every frame as ``<t_ns>.png`` (:func:`depth_image_name`: 19
    zero-padded digits; uint16, millimetres, 0 = none) plus ``depth.json`` (scale, camera,
    intrinsics). Returns the number of images written."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    camera = seq.calibration.cameras[cam]
    meta = {
        "depth_scale_m": DEPTH_SCALE_M,
        "camera": camera.to_dict(),
        "note": "z in the camera frame, distorted pixel grid of the camera; 0 = no depth",
    }
    write_atomic(out / "depth.json", json.dumps(meta, indent=2).encode())
    times = seq.frame_times_ns()
    for i in tqdm(range(len(times)), desc=f"depth {out.name}", unit="frame", disable=not progress):
        depth_m = seq.depth(i, cam)
        mm = np.clip(np.round(depth_m / DEPTH_SCALE_M), 0, 65535).astype(np.uint16)
        ok, buf = cv2.imencode(".png", mm)
        if not ok:
            raise OSError(f"cannot encode depth image {i}")
        write_atomic(out / depth_image_name(int(times[i])), buf.tobytes())
    return len(times)


@dataclass(frozen=True)
class SynthResult:
    """What ``slam synth`` wrote."""

    mcap_path: Path
    num_frames: int
    num_imu: int
    duration_s: float
    path_length_m: float
    depth_images: int = 0
    mesh_path: Path | None = None
    gyro_agreement: GyroAgreement | None = None  # with a real IMU (--imu-csv)
    accel_scale: AccelScale | None = None  # with a real IMU (--imu-csv)


def run_synth(
    out_mcap: str | os.PathLike[str],
    *,
    profile: str = "figure8",
    duration_s: float | None = None,
    seed: int = 0,
    scene_seed: int = 0,
    trajectory_file: str | None = None,
    imu_csv: str | None = None,
    imu_csv_on_trajectory: bool = False,
    imu_noise: bool = True,
    blackout: tuple[float, float] | None = None,
    moving_start: bool = False,
    aliasing: bool = False,
    pixel_noise_std: float = 0.0,
    gyro_bias0_rad_s: tuple[float, float, float] | None = None,
    accel_bias0_m_s2: tuple[float, float, float] | None = None,
    depth_dir: str | os.PathLike[str] | None = None,
    mesh_path: str | os.PathLike[str] | None = None,
    progress: bool = True,
    camera: CameraEffects | None = None,
    imu_effects: ImuEffects | None = None,
    time_offset_ns: int = 0,
    calib_rotation_error_deg: tuple[float, float, float] | None = None,
) -> SynthResult:
    """Make a synthetic sequence and write it as MCAP (+ optional depth PNGs and PLY mesh)."""
    from datasets.mcap_io import write_sequence_mcap
    from datasets.synth.generator import make_synthetic_sequence

    seq = make_synthetic_sequence(
        profile,
        duration_s,
        seed,
        imu_noise=imu_noise,
        blackout=blackout,
        moving_start=moving_start,
        aliasing=aliasing,
        pixel_noise_std=pixel_noise_std,
        scene_seed=scene_seed,
        trajectory_file=trajectory_file,
        imu_csv=imu_csv,
        imu_csv_on_trajectory=imu_csv_on_trajectory,
        gyro_bias0_rad_s=None if gyro_bias0_rad_s is None else np.asarray(gyro_bias0_rad_s),
        accel_bias0_m_s2=None if accel_bias0_m_s2 is None else np.asarray(accel_bias0_m_s2),
        camera=camera,
        imu_effects=imu_effects,
        time_offset_ns=time_offset_ns,
        calib_rotation_error_deg=calib_rotation_error_deg,
    )
    out = Path(out_mcap)
    write_sequence_mcap(seq, out, progress=progress)
    n_depth = write_depth_images(seq, depth_dir, progress=progress) if depth_dir else 0
    if mesh_path is not None:
        verts, tris = seq.scene_mesh()
        write_ply_mesh(mesh_path, verts, tris, comment="pyvislam synthetic scene (world frame)")
    gt = seq.ground_truth
    assert gt is not None
    return SynthResult(
        mcap_path=out,
        num_frames=seq.num_frames,
        num_imu=seq.num_imu,
        duration_s=seq.duration_ns * 1e-9,
        path_length_m=gt.path_length_m(),
        depth_images=n_depth,
        mesh_path=Path(mesh_path) if mesh_path is not None else None,
        gyro_agreement=seq.gyro_agreement,
        accel_scale=seq.accel_scale,
    )

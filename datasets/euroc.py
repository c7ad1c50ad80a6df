"""EuRoC MAV and TUM-VI folders (the ASL layout) read directly as a :class:`Sequence`.

Layout: ``mav0/cam0/{data.csv,data/*.png,sensor.yaml}``, ``mav0/cam1/...``,
``mav0/imu0/{data.csv,sensor.yaml}``, ground truth in ``mav0/state_groundtruth_estimate0/data.csv``
(EuRoC) or ``mav0/mocap0/data.csv`` (TUM-VI). ``sensor.yaml`` files may start with OpenCV's
``%YAML:1.0``; ``T_BS`` is body_from_sensor in the dataset's body frame. Our body is the IMU, so
``imu_from_cam = inv(T_BS_imu) @ T_BS_cam`` and ground truth is moved to the IMU the same way.

Images are loaded lazily (``cv2.imread(..., IMREAD_GRAYSCALE)``); every listed file is checked to
exist when the folder is opened: a frame with a missing image (left or right) is skipped, counted
and named in a warning (``strict=True``: refused, by name).
Timestamps are parsed as integers (a float64 cannot hold 19-digit nanoseconds exactly).
"""

from __future__ import annotations

import os
from pathlib import Path

import cv2
import numpy as np

from datasets.kalibr import distortion_model, load_yaml
from datasets.sequence import ImuArrays, Sequence
from datasets.timing import find_gaps, pair_stereo, sort_dedupe
from slam.core.calibration import Calibration, CameraCalibration, CameraIntrinsics, ImuCalibration
from slam.core.errors import InputError
from slam.core.geometry import invert_transform
from slam.core.messages import StereoFrame
from slam.core.trajectory import Trajectory
from slam.evaluation.io import detect_format, read_trajectory

GT_CANDIDATES = ("state_groundtruth_estimate0", "mocap0")


def find_mav0(path: str | os.PathLike[str]) -> Path | None:
    """The ``mav0`` folder of an ASL dataset given it or its parent, else None."""
    p = Path(path)
    for cand in (p / "mav0", p):
        if (cand / "cam0" / "data.csv").is_file():
            return cand
    return None


def read_csv_rows(path: str | os.PathLike[str]) -> tuple[np.ndarray, list[list[str]]]:
    """An ASL csv: (int64 first column, remaining columns as strings); '#' lines skipped."""
    times: list[int] = []
    rows: list[list[str]] = []
    try:
        with open(path, encoding="utf-8") as fh:
            for lineno, line in enumerate(fh, 1):
                line = line.strip()
                if not line or line.startswith("#"):
                    continue
                parts = [x.strip() for x in line.split(",")]
                try:
                    times.append(int(parts[0]))
                except ValueError as exc:
                    raise InputError(
                        f"{path}:{lineno}: first column is not an integer timestamp in ns"
                    ) from exc
                rows.append(parts[1:])
    except OSError as exc:
        raise InputError(f"cannot read {path}: {exc.strerror}") from exc
    return np.asarray(times, dtype=np.int64), rows


def _floats(rows: list[list[str]], ncols: int, path: str | os.PathLike[str]) -> np.ndarray:
    try:
        return np.array([[float(x) for x in r[:ncols]] for r in rows], dtype=float).reshape(
            -1, ncols
        )
    except ValueError as exc:
        raise InputError(
            f"{path}: expected {ncols} numeric columns after the time ({exc})"
        ) from exc


def sensor_T_BS(data: dict, where: str) -> np.ndarray:  # noqa: N802 - the dataset's name
    """``T_BS`` (body_from_sensor) of a sensor.yaml, identity when absent."""
    t = data.get("T_BS")
    if t is None:
        return np.eye(4)
    values = t.get("data") if isinstance(t, dict) else t
    try:
        return np.asarray(values, dtype=float).reshape(4, 4)
    except (TypeError, ValueError) as exc:
        raise InputError(f"{where}: T_BS is not a 4x4 matrix") from exc


def read_camera_yaml(
    path: str | os.PathLike[str], name: str
) -> tuple[CameraIntrinsics, np.ndarray, float]:
    """A camera sensor.yaml -> (intrinsics, T_BS, rate_hz)."""
    where = os.fspath(path)
    d = load_yaml(path)
    try:
        if str(d.get("camera_model", "pinhole")) != "pinhole":
            raise InputError(f"{where}: camera_model {d.get('camera_model')!r} not supported")
        fu, fv, cu, cv = (float(x) for x in d["intrinsics"])
        width, height = (int(x) for x in d["resolution"])
        model = distortion_model(d.get("distortion_model", "none"), where)
        coeffs = tuple(float(x) for x in d.get("distortion_coefficients", ()))
        rate = float(d.get("rate_hz", 20.0))
    except (KeyError, TypeError, ValueError) as exc:
        raise InputError(f"{where}: missing or malformed camera field ({exc})") from exc
    intr = CameraIntrinsics(width, height, fu, fv, cu, cv, model, coeffs)
    return intr, sensor_T_BS(d, where), rate


def read_imu_yaml(path: str | os.PathLike[str]) -> tuple[ImuCalibration, np.ndarray]:
    """An IMU sensor.yaml -> (noise model, T_BS)."""
    where = os.fspath(path)
    d = load_yaml(path)
    default = ImuCalibration()
    try:
        imu = ImuCalibration(
            rate_hz=float(d.get("rate_hz", default.rate_hz)),
            gyro_noise_density=float(d.get("gyroscope_noise_density", default.gyro_noise_density)),
            gyro_random_walk=float(d.get("gyroscope_random_walk", default.gyro_random_walk)),
            accel_noise_density=float(
                d.get("accelerometer_noise_density", default.accel_noise_density)
            ),
            accel_random_walk=float(d.get("accelerometer_random_walk", default.accel_random_walk)),
        )
    except (TypeError, ValueError) as exc:
        raise InputError(f"{where}: malformed IMU noise field ({exc})") from exc
    return imu, sensor_T_BS(d, where)


def read_euroc_imu(path: str | os.PathLike[str]) -> ImuArrays:
    """``imu0/data.csv``: time, w_x, w_y, w_z (rad/s), a_x, a_y, a_z (m/s^2), as stored."""
    t, rows = read_csv_rows(path)
    vals = _floats(rows, 6, path)
    return ImuArrays(t, np.ascontiguousarray(vals[:, :3]), np.ascontiguousarray(vals[:, 3:6]))


def read_euroc_groundtruth_full(
    path: str | os.PathLike[str],
) -> tuple[Trajectory, np.ndarray, np.ndarray, np.ndarray]:
    """EuRoC ground-truth csv -> (world_from_body, velocities_m_s, bias_gyro_rad_s, bias_accel_m_s2).

    Columns: time ns, p xyz, q wxyz, v xyz, b_w xyz, b_a xyz (``state_groundtruth_estimate0`` and
    OpenVINS' recomputed files). Rows are sorted and de-duplicated by time. Frames as stored (the
    EuRoC ground-truth body is the IMU: its T_BS is identity).
    """
    t, rows = read_csv_rows(path)
    vals = _floats(rows, 16, path)
    keep = sort_dedupe(t).keep
    t, vals = t[keep], vals[keep]
    q = vals[:, 3:7] / np.linalg.norm(vals[:, 3:7], axis=1, keepdims=True)
    traj = Trajectory(t, np.ascontiguousarray(vals[:, 0:3]), q)
    return (
        traj,
        np.ascontiguousarray(vals[:, 7:10]),
        np.ascontiguousarray(vals[:, 10:13]),
        np.ascontiguousarray(vals[:, 13:16]),
    )


def read_trajectory_file(path: str | os.PathLike[str]) -> Trajectory:
    """A ground-truth file: EuRoC/ASL csv (time ns, p xyz, q wxyz, ...) or TUM text
    (time s, p xyz, q xyzw, space separated), read by :mod:`slam.evaluation.io` (the project's
    one reader of both formats). Rows sorted by time; of repeated times the first row is kept;
    near-unit quaternions normalised without a warning."""
    p = Path(path)
    if not p.is_file():
        raise InputError(f"trajectory file not found: {p}")
    fmt = detect_format(p)
    if fmt not in ("tum", "euroc"):
        raise InputError(f"{p}: not a trajectory file (TUM text or EuRoC csv)")
    return read_trajectory(p, fmt, duplicates="first", sort=True, quiet=True).trajectory


class EurocSequence(Sequence):
    """An EuRoC / TUM-VI ASL folder (stereo or mono, IMU, optional ground truth)."""

    def __init__(
        self,
        path: str | os.PathLike[str],
        *,
        gt_path: str | os.PathLike[str] | None = None,
        pair_tolerance_ns: int = 2_000_000,
        strict: bool = False,
    ) -> None:
        mav0 = find_mav0(path)
        if mav0 is None:
            raise InputError(f"{path}: not an ASL folder (expected mav0/cam0/data.csv)")
        self.root = mav0
        warnings: list[str] = []

        imu_dir = mav0 / "imu0"
        if (imu_dir / "sensor.yaml").is_file():
            imu_cal, imu_T_BS = read_imu_yaml(imu_dir / "sensor.yaml")  # noqa: N806
        else:
            imu_cal, imu_T_BS = ImuCalibration(), np.eye(4)  # noqa: N806
            warnings.append("imu0/sensor.yaml missing: default (EuRoC ADIS16448) noise model used")
        imu_from_B = invert_transform(imu_T_BS)  # noqa: N806

        cams: list[CameraCalibration] = []
        cam_times: list[np.ndarray] = []
        cam_files: list[list[Path]] = []
        for name in ("cam0", "cam1"):
            cdir = mav0 / name
            if not (cdir / "data.csv").is_file():
                continue
            intr, T_BS, rate = read_camera_yaml(cdir / "sensor.yaml", name)  # noqa: N806
            cams.append(CameraCalibration(name, intr, imu_from_B @ T_BS, rate))
            t, rows = read_csv_rows(cdir / "data.csv")
            files = [cdir / "data" / (r[0] if r else f"{tt}.png") for tt, r in zip(t, rows)]
            cleaned = sort_dedupe(t)
            note = cleaned.describe(f"{name}/data.csv")
            if note:
                warnings.append(note)
            cam_times.append(t[cleaned.keep])
            cam_files.append([files[i] for i in cleaned.keep])

        if len(cams) == 2:
            pairing = pair_stereo(cam_times[0], cam_times[1], pair_tolerance_ns)
            if pairing.unmatched_left or pairing.unmatched_right:
                warnings.append(
                    f"stereo pairing: {pairing.unmatched_left} cam0 and "
                    f"{pairing.unmatched_right} cam1 rows had no partner and were dropped"
                )
            self._t_ns = cam_times[0][pairing.left]
            self._left = [cam_files[0][i] for i in pairing.left]
            self._right: list[Path] | None = [cam_files[1][i] for i in pairing.right]
        else:
            self._t_ns = cam_times[0]
            self._left = cam_files[0]
            self._right = None
        missing = self._drop_missing_images(strict)
        if missing:
            warnings.append(missing)

        if (imu_dir / "data.csv").is_file():
            raw = read_euroc_imu(imu_dir / "data.csv")
            cleaned = sort_dedupe(raw.t_ns)
            note = cleaned.describe("imu0/data.csv")
            if note:
                warnings.append(note)
            k = cleaned.keep
            self._imu = ImuArrays(raw.t_ns[k], raw.gyro_rad_s[k], raw.accel_m_s2[k])
            gaps = find_gaps(self._imu.t_ns).describe("imu0")
            if gaps:
                warnings.append(gaps)
        else:
            self._imu = ImuArrays(np.zeros(0, np.int64), np.zeros((0, 3)), np.zeros((0, 3)))
            warnings.append("no imu0/data.csv: camera-only sequence")

        ground_truth = None
        if gt_path is not None:
            ground_truth = read_trajectory_file(gt_path)
        else:
            for cand in GT_CANDIDATES:
                csv = mav0 / cand / "data.csv"
                if csv.is_file():
                    traj = read_trajectory_file(csv)
                    yaml_path = mav0 / cand / "sensor.yaml"
                    gt_T_BS = (  # noqa: N806
                        sensor_T_BS(load_yaml(yaml_path), str(yaml_path))
                        if yaml_path.is_file()
                        else np.eye(4)
                    )
                    s_from_imu = invert_transform(gt_T_BS) @ imu_T_BS
                    if not np.allclose(s_from_imu, np.eye(4)):
                        traj = Trajectory.from_matrices(traj.t_ns, traj.matrices() @ s_from_imu)
                    ground_truth = traj
                    break

        name = mav0.parent.name if mav0.name == "mav0" else mav0.name
        super().__init__(
            name=name,
            calibration=Calibration(tuple(cams), imu_cal, 0),
            ground_truth=ground_truth,
        )
        for w in warnings:
            self.warn(w)

    def _drop_missing_images(self, strict: bool) -> str | None:
        """Skip the frames whose left or right image file is missing; a warning naming them
        (None when all are there). ``strict``: raise instead."""
        ok = np.array(
            [
                self._left[i].is_file() and (self._right is None or self._right[i].is_file())
                for i in range(len(self._left))
            ],
            dtype=bool,
        )
        if ok.all():
            return None
        absent = [
            f
            for i in np.nonzero(~ok)[0]
            for f in (self._left[i], *([self._right[i]] if self._right is not None else []))
            if not f.is_file()
        ]
        listed = absent[0].parent.parent / "data.csv"
        if strict:
            raise InputError(
                f"image file missing: {absent[0]} (listed in {listed}); run without --strict "
                "to skip the frames whose images are missing"
            )
        if not ok.any():
            raise InputError(
                f"none of the {len(ok)} frames listed in {listed} has its image files (the "
                f"first missing: {absent[0]}); is the data/ folder there?"
            )
        names = ", ".join(f"{f.parent.parent.name}/{f.name}" for f in absent[:5])
        more = f" and {len(absent) - 5} more" if len(absent) > 5 else ""
        keep = np.nonzero(ok)[0]
        self._t_ns = self._t_ns[keep]
        self._left = [self._left[i] for i in keep]
        if self._right is not None:
            self._right = [self._right[i] for i in keep]
        return (
            f"{int((~ok).sum())} frame(s) skipped: image file missing: {names}{more} "
            "(listed in data.csv; --strict refuses the folder instead)"
        )

    def frame_times_ns(self) -> np.ndarray:
        return self._t_ns

    def imu(self) -> ImuArrays:
        return self._imu

    def frame(self, index: int) -> StereoFrame:
        left = _imread(self._left[index])
        right = _imread(self._right[index]) if self._right is not None else None
        return StereoFrame(int(self._t_ns[index]), left, right, index)


def _imread(path: Path) -> np.ndarray:
    img = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
    if img is None:
        raise InputError(f"image file unreadable: {path}")
    return img

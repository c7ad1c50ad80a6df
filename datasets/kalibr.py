"""Kalibr calibration files -> :class:`Calibration`.

``camchain.yaml`` (``kalibr_calibrate_cameras`` / ``kalibr_calibrate_imu_camera`` output): per
camera ``camera_model: pinhole``, ``intrinsics: [fu, fv, pu, pv]``, ``distortion_model``
(``radtan`` or ``equidistant``), ``distortion_coeffs``, ``resolution``, ``T_cam_imu``
(cam_from_imu; our body is the IMU, so body_from_cam is its inverse), ``timeshift_cam_imu``
(seconds, ``t_imu = t_cam + shift``), ``rostopic``.

``imu.yaml``: ``accelerometer_noise_density``, ``accelerometer_random_walk``,
``gyroscope_noise_density``, ``gyroscope_random_walk``, ``update_rate``, ``rostopic`` (either at
top level or under ``imu0``).
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from typing import Any

import numpy as np
import yaml

from slam.core.calibration import Calibration, CameraCalibration, CameraIntrinsics, ImuCalibration
from slam.core.errors import InputError
from slam.core.geometry import invert_transform

DISTORTION_ALIASES = {
    "radtan": "radtan",
    "radial-tangential": "radtan",
    "plumb_bob": "radtan",
    "equidistant": "equidistant",
    "equi": "equidistant",
    "fisheye": "equidistant",
    "none": "none",
}


@dataclass(frozen=True)
class KalibrCalibration:
    """The calibration plus the topics Kalibr recorded it from (when present)."""

    calibration: Calibration
    camera_topics: tuple[str | None, ...]
    imu_topic: str | None


def load_yaml(path: str | os.PathLike[str]) -> dict[str, Any]:
    """Load a YAML mapping; tolerates OpenCV's ``%YAML:1.0`` first line."""
    path = os.fspath(path)
    try:
        with open(path, encoding="utf-8") as fh:
            text = fh.read()
    except OSError as exc:
        raise InputError(f"cannot read {path}: {exc.strerror}") from exc
    lines = [ln for ln in text.splitlines() if not ln.startswith("%YAML")]
    try:
        data = yaml.safe_load("\n".join(lines))
    except yaml.YAMLError as exc:
        raise InputError(f"{path} is not valid YAML: {exc}") from exc
    if not isinstance(data, dict):
        raise InputError(f"{path} does not hold a YAML mapping")
    return data


def distortion_model(name: str, where: str) -> str:
    model = DISTORTION_ALIASES.get(str(name).lower())
    if model is None:
        raise InputError(
            f"{where}: distortion model {name!r} not supported (radtan/radial-tangential, "
            "equidistant)"
        )
    return model


def _camera(name: str, d: dict[str, Any], where: str) -> tuple[CameraCalibration, float]:
    try:
        model = str(d.get("camera_model", "pinhole"))
        if model != "pinhole":
            raise InputError(f"{where}: {name} camera_model {model!r} not supported (pinhole)")
        fu, fv, pu, pv = (float(x) for x in d["intrinsics"])
        width, height = (int(x) for x in d["resolution"])
        dist = distortion_model(d.get("distortion_model", "none"), f"{where} {name}")
        coeffs = tuple(float(x) for x in d.get("distortion_coeffs", ()))
        cam_from_imu = np.asarray(d["T_cam_imu"], dtype=float).reshape(4, 4)
        shift_s = float(d.get("timeshift_cam_imu", 0.0))
    except (KeyError, TypeError, ValueError) as exc:
        raise InputError(f"{where}: {name} is missing or has a malformed field ({exc})") from exc
    intr = CameraIntrinsics(width, height, fu, fv, pu, pv, dist, coeffs)
    return CameraCalibration(name, intr, invert_transform(cam_from_imu)), shift_s


def load_imu_yaml(path: str | os.PathLike[str]) -> tuple[ImuCalibration, str | None]:
    """Kalibr imu.yaml -> (noise model, rostopic)."""
    data = load_yaml(path)
    d = data.get("imu0", data)
    try:
        imu = ImuCalibration(
            rate_hz=float(d.get("update_rate", 200.0)),
            gyro_noise_density=float(d["gyroscope_noise_density"]),
            gyro_random_walk=float(d["gyroscope_random_walk"]),
            accel_noise_density=float(d["accelerometer_noise_density"]),
            accel_random_walk=float(d["accelerometer_random_walk"]),
        )
    except (KeyError, TypeError, ValueError) as exc:
        raise InputError(f"{path}: missing or malformed IMU noise field ({exc})") from exc
    return imu, d.get("rostopic")


def load_kalibr(
    camchain: str | os.PathLike[str], imu_yaml: str | os.PathLike[str] | None = None
) -> KalibrCalibration:
    """camchain.yaml (+ optional imu.yaml) -> calibration and the recorded topics."""
    where = os.fspath(camchain)
    data = load_yaml(camchain)
    names = sorted((k for k in data if k.startswith("cam")), key=lambda k: int(k[3:] or 0))
    if not names:
        raise InputError(f"{where}: no cam0/cam1 entries; is this a Kalibr camchain.yaml?")
    cams, shifts, topics = [], [], []
    for name in names:
        cam, shift = _camera(name, data[name], where)
        cams.append(cam)
        shifts.append(shift)
        topics.append(data[name].get("rostopic"))
    imu, imu_topic = load_imu_yaml(imu_yaml) if imu_yaml is not None else (None, None)
    calib = Calibration(tuple(cams), imu, time_offset_ns=round(shifts[0] * 1e9))
    return KalibrCalibration(calib, tuple(topics), imu_topic)

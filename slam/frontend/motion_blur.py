"""Motion blur predicted from the gyro and the exposure time.

While the shutter is open (``StereoFrame.exposure_ns``, E) the camera turns by the gyro's rate
omega, and every image point is smeared along its flow: a streak of about ``f * |omega_perp| * E``
pixels (``f`` the focal length, ``omega_perp`` the rate about the axes across the point's ray;
about the ray the point turns around the principal point instead). The image, stamped at
mid-exposure (``player.mid_exposure``), shows the streak's centre: a blurred feature is not
biased, but located less precisely along the streak (KLT's error grows with it).

Only rotation is modelled: at room-aggressive's 3 rad/s a 10 ms exposure smears a point by
~14 px, while 1 m/s at 2 m moves it by ~2 px. The rate is the gyro's over the half-exposure
before the image's (mid-exposure) time, the part the front end has when the frame arrives,
taken as constant over the whole exposure.

Used by the front end: a blurred frame's PnP pose leans on the IMU's prediction
(``frontend.blur_pose_prior_min_px``). A frame of unknown exposure (0) has no predicted blur
(0), so sequences without exposures behave as before.
"""

from __future__ import annotations

import numpy as np

from slam.core.calibration import CameraIntrinsics
from slam.core.geometry import so3_exp, so3_log
from slam.imu_buffer import ImuBuffer, integrate_gyro

MIN_RATE_SPAN_NS = 2_000_000
"""The gyro's rate is averaged over at least this long (a 0.2 ms exposure's half would fall
between two samples of a 200 Hz IMU: the one sample covering it is taken as it is)."""


def angular_rate_rad_s(
    imu: ImuBuffer,
    t_ns: int,
    exposure_ns: int,
    bias_gyro_rad_s: np.ndarray | None = None,
) -> np.ndarray | None:
    """The body's mean angular rate (3,), rad/s in the body frame, over
    ``[t - max(E/2, 2 ms), t]`` (``t`` the image's mid-exposure time, ``E`` its exposure), bias
    removed; None when ``imu``'s samples do not cover it."""
    span_ns = max(exposure_ns // 2, MIN_RATE_SPAN_NS)
    t0_ns = t_ns - span_ns
    body0_from_body1 = integrate_gyro(imu.window(t0_ns, t_ns), t0_ns, t_ns, bias_gyro_rad_s)
    if body0_from_body1 is None:
        return None
    return np.asarray(so3_log(body0_from_body1), dtype=float) / (span_ns * 1e-9)


def blur_vectors_px(
    rate_body_rad_s: np.ndarray,
    exposure_s: float,
    cam_from_body_rotation: np.ndarray,
    intrinsics: CameraIntrinsics,
    pixels: np.ndarray,
    normalised: np.ndarray | None = None,
) -> np.ndarray:
    """The streak (N, 2), px, each pixel (N, 2, distorted, as seen at mid-exposure) of a static
    scene is smeared over by a constant body rate over the exposure: its pixel at the exposure's
    end minus its pixel at the start (rows of points that leave the front of the camera: 0).
    ``normalised``: the pixels' ``intrinsics.undistort_points``, where the caller has them."""
    px = np.asarray(pixels, dtype=float).reshape(-1, 2)
    if len(px) == 0 or exposure_s <= 0:
        return np.zeros((len(px), 2))
    rate_cam = cam_from_body_rotation @ np.asarray(rate_body_rad_s, dtype=float)
    # cam(mid)_from_cam(end) = exp(w E/2): a point p (mid camera) is at R^T p at the end, R p at
    # the start
    mid_from_end = so3_exp(rate_cam * (0.5 * exposure_s))
    norm = intrinsics.undistort_points(px) if normalised is None else normalised
    rays = np.hstack([norm, np.ones((len(px), 1))])
    end = rays @ mid_from_end  # rows: R^T p
    start = rays @ mid_from_end.T  # rows: R p
    front = (end[:, 2] > 1e-3) & (start[:, 2] > 1e-3)
    out = np.zeros((len(px), 2))
    if front.any():
        out[front] = intrinsics.project(end[front]) - intrinsics.project(start[front])
    return out


def blur_length_px(
    rate_body_rad_s: np.ndarray,
    exposure_s: float,
    cam_from_body_rotation: np.ndarray,
    intrinsics: CameraIntrinsics,
    pixels: np.ndarray,
    normalised: np.ndarray | None = None,
) -> float:
    """One number for a frame: the median streak length (px) over ``pixels`` (its features),
    or over a 3x3 grid of the image when there are none; 0 for no exposure. ``normalised``:
    the pixels' ``intrinsics.undistort_points``, where the caller has them."""
    px = np.asarray(pixels, dtype=float).reshape(-1, 2)
    if exposure_s <= 0:
        return 0.0
    if len(px) == 0:
        gx = (np.arange(3) + 0.5) * intrinsics.width / 3
        gy = (np.arange(3) + 0.5) * intrinsics.height / 3
        px = np.array([(x, y) for y in gy for x in gx])
        normalised = None
    vec = blur_vectors_px(
        rate_body_rad_s, exposure_s, cam_from_body_rotation, intrinsics, px, normalised
    )
    return float(np.median(np.linalg.norm(vec, axis=1)))

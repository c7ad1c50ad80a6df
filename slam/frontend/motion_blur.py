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


def rate_turn(
    imu: ImuBuffer,
    t_ns: int,
    exposure_ns: int,
    bias_gyro_rad_s: np.ndarray | None = None,
) -> tuple[np.ndarray, float] | None:
    """The body's turn over ``[t - max(E/2, 2 ms), t]`` (``t`` the image's mid-exposure time,
    ``E`` its exposure), bias removed: (body(t0)_from_body(t) (3, 3), the span in s), or None
    when ``imu``'s samples do not cover it (:func:`angular_rate_rad_s` is its rotation vector
    over the span)."""
    span_ns = max(exposure_ns // 2, MIN_RATE_SPAN_NS)
    t0_ns = t_ns - span_ns
    body0_from_body1 = integrate_gyro(imu.window(t0_ns, t_ns), t0_ns, t_ns, bias_gyro_rad_s)
    if body0_from_body1 is None:
        return None
    return body0_from_body1, span_ns * 1e-9


def angular_rate_rad_s(
    imu: ImuBuffer,
    t_ns: int,
    exposure_ns: int,
    bias_gyro_rad_s: np.ndarray | None = None,
) -> np.ndarray | None:
    """The body's mean angular rate (3,), rad/s in the body frame, over
    ``[t - max(E/2, 2 ms), t]`` (``t`` the image's mid-exposure time, ``E`` its exposure), bias
    removed; None when ``imu``'s samples do not cover it."""
    turn = rate_turn(imu, t_ns, exposure_ns, bias_gyro_rad_s)
    if turn is None:
        return None
    return np.asarray(so3_log(turn[0]), dtype=float) / turn[1]


MAX_BOUNDED_TURN_RAD = 0.2
"""The largest turn over an exposure (|omega| E) :class:`BlurBound` bounds the streaks of (inf
beyond it): 20 rad/s over 10 ms."""


class BlurBound:
    """Upper bounds of the pixels' streaks (:func:`blur_vectors_px`) from the turn over the
    exposure alone, and so of :func:`blur_length_px` (the median of the bounds).

    Why: the front end needs a frame's blur only where it is above a threshold
    (``frontend.blur_pose_prior_min_px``); the bounds tell most frames of a slow sequence apart
    without the rate's rotation vector and the streaks.

    A streak joins the projections of a pixel's ray turned by +-omega E / 2: two rays at most
    |omega| E apart, both within |omega| E / 2 of the pixel's ray, as is the shorter arc between
    them. Along it the projection moves at most ``L(a + |omega| E / 2)`` pixels per radian the ray
    turns, ``a`` the ray's angle from the optical axis and ``L(b)`` the largest rate of
    ``intrinsics.project`` over the rays within ``b`` of the axis (sampled on a grid of
    directions, plus 25 % for between the samples): the streak is at most
    ``L(a + |omega| E / 2) |omega| E``. Tabulated up to the image's widest ray plus
    ``MAX_BOUNDED_TURN_RAD``; beyond it (or a field of view past 75 degrees) the bound is inf."""

    def __init__(self, intrinsics: CameraIntrinsics, bins: int = 32, azimuths: int = 72) -> None:
        w, h = intrinsics.width, intrinsics.height
        xs = np.linspace(0.0, w - 1.0, max(w // 4, 2))
        ys = np.linspace(0.0, h - 1.0, max(h // 4, 2))
        pixels = np.concatenate(
            [
                np.stack([xs, np.zeros_like(xs)], 1),
                np.stack([xs, np.full_like(xs, h - 1.0)], 1),
                np.stack([np.zeros_like(ys), ys], 1),
                np.stack([np.full_like(ys, w - 1.0), ys], 1),
                np.stack(np.meshgrid(xs[::8], ys[::8]), -1).reshape(-1, 2),
            ]
        )
        widest = float(np.arctan(np.linalg.norm(intrinsics.undistort_points(pixels), axis=1).max()))
        top = widest + MAX_BOUNDED_TURN_RAD
        self.edges_rad = np.linspace(0.0, top, bins + 1)
        self.px_per_rad = np.full(bins + 1, np.inf)
        """``L`` at each edge: the largest rate of the projection within that angle of the axis."""
        if not np.isfinite(top) or top >= np.radians(75.0):
            return
        polar_grid, azimuth_grid = np.meshgrid(
            np.linspace(0.0, top, 4 * bins + 1), np.linspace(0.0, 2 * np.pi, azimuths)
        )
        polar, azimuth = polar_grid.ravel(), azimuth_grid.ravel()
        sin_p, cos_p, sin_a, cos_a = np.sin(polar), np.cos(polar), np.sin(azimuth), np.cos(azimuth)
        rays = np.stack([sin_p * cos_a, sin_p * sin_a, cos_p], 1)
        along_polar = np.stack([cos_p * cos_a, cos_p * sin_a, -sin_p], 1)
        along_azimuth = np.stack([-sin_a, cos_a, np.zeros_like(azimuth)], 1)
        step = 1e-6
        at = intrinsics.project(rays)
        jac = np.stack(
            [
                (intrinsics.project(rays + step * along_polar) - at) / step,
                (intrinsics.project(rays + step * along_azimuth) - at) / step,
            ],
            axis=2,
        )
        rate = np.linalg.norm(jac, ord=2, axis=(1, 2))  # the largest singular value per ray
        if not np.isfinite(rate).all():
            return
        # the largest rate at or inside each edge: polar samples 4 per bin, each edge one of them
        ring = rate.reshape(azimuths, 4 * bins + 1).max(axis=0)
        self.px_per_rad = 1.25 * np.maximum.accumulate(ring)[::4]

    def lowest_px(self, turn_rad: float) -> float:
        """The smallest bound any pixel can have for a turn of ``turn_rad``: where it is above
        a threshold, so is :meth:`length_px`."""
        return float(self.px_per_rad[0]) * turn_rad

    def length_px(self, normalised: np.ndarray, turn_rad: float) -> float:
        """A bound of :func:`blur_length_px` (px) for pixels at ``normalised`` (N, 2, undistorted
        normalised coordinates, N > 0) and a turn of ``turn_rad`` (|omega| E) over the exposure."""
        if turn_rad > MAX_BOUNDED_TURN_RAD:
            return np.inf
        angle = np.arctan(np.hypot(normalised[:, 0], normalised[:, 1])) + 0.5 * turn_rad
        edge = np.searchsorted(self.edges_rad, angle)  # the first edge at or beyond the ray
        rate = self.px_per_rad[np.minimum(edge, len(self.edges_rad) - 1)]
        rate = np.where(edge < len(self.edges_rad), rate, np.inf)
        return float(np.median(rate)) * turn_rad


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

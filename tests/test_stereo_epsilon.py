"""KLT's stopping tolerance leaves a match short of its optimum on the side of its start
(slam/frontend/features.py ``track_klt``, ``frontend.stereo_klt_epsilon_px``): the map's scale
hangs on stereo disparities to a few thousandths of a pixel (BENCHMARKS.md, branch hall17)."""

from __future__ import annotations

import dataclasses

import cv2
import numpy as np

from datasets.rigs import euroc_like_calibration
from slam.config import load_config
from slam.frontend.features import track_klt
from slam.frontend.stereo import StereoMatcher


def _texture(seed: int = 0, shape: tuple[int, int] = (480, 752)) -> np.ndarray:
    """Smooth random texture, 20-220 grey levels (float32)."""
    rng = np.random.default_rng(seed)
    img = cv2.GaussianBlur(rng.uniform(0, 255, shape).astype(np.float32), (0, 0), 2.0)
    return (img - img.min()) / (img.max() - img.min()) * 200 + 20


def _shifted(img: np.ndarray, dx_px: float) -> np.ndarray:
    """``img`` moved by ``dx_px`` along x, exactly for its band-limited content (Fourier)."""
    fx = np.fft.fftfreq(img.shape[1])
    return np.real(np.fft.ifft2(np.fft.fft2(img) * np.exp(-2j * np.pi * fx * dx_px)[None, :]))


def _grid(x0: int, x1: int, y0: int, y1: int, step: int = 30) -> np.ndarray:
    return np.array([[x, y] for x in range(x0, x1, step) for y in range(y0, y1, step)], np.float32)


def test_klt_stops_short_on_the_side_of_its_start_unless_the_tolerance_is_tight() -> None:
    """The same match started 2 px to the left and 2 px to the right of the truth (a 10.37 px
    disparity): at the default 0.03 px tolerance the two ends differ by ~2e-3 px on average
    (each short of the optimum towards its start), at 0.001 px by < 2e-4 px."""
    cfg = load_config("euroc-stereo-imu").frontend
    img = _texture(5)
    dx = -10.37
    left = np.round(img).astype(np.uint8)
    right = np.clip(np.round(_shifted(img, dx)), 0, 255).astype(np.uint8)
    pts = _grid(60, 690, 60, 420)
    spread = {}
    for eps in (0.03, 0.001):
        ends = []
        for start in (-2.0, 2.0):
            px, ok = track_klt(
                left,
                right,
                pts,
                cfg,
                guess_to=pts + [dx + start, 0.0],
                levels=0,
                backward_check=False,
                epsilon_px=eps,
            )
            assert ok.all()
            assert np.abs(px[:, 0] - (pts[:, 0] + dx)).max() < 0.05
            ends.append(px[:, 0].astype(np.float64))
        spread[eps] = float(np.mean(ends[1] - ends[0]))
    assert spread[0.03] > 1e-3  # the right start ends further right
    assert abs(spread[0.001]) < 2e-4


def test_stereo_matcher_takes_the_tolerance_from_the_config() -> None:
    """Tracked landmarks believed 3 % nearer or farther than the textured plane 3 m in front
    of the rig start their right-image match there: at the default tolerance the mean
    disparity depends on that belief (> 5e-4 px), with ``stereo_klt_epsilon_px`` 0.001 it does
    not (< 2e-4 px)."""
    calib = euroc_like_calibration(distortion=False)
    cam0, cam1 = calib.cameras[0].intrinsics, calib.cameras[1].intrinsics
    c1_from_c0 = calib.cam1_from_cam0()
    depth_m = 3.0
    h = cam1.K @ (c1_from_c0[:3, :3] + np.outer(c1_from_c0[:3, 3], [0, 0, 1.0 / depth_m]))
    h = h @ np.linalg.inv(cam0.K)
    left = _texture(3)
    right = cv2.warpPerspective(left, h, (752, 480), flags=cv2.INTER_CUBIC)
    left_u8 = np.round(left).astype(np.uint8)
    right_u8 = np.clip(np.round(right), 0, 255).astype(np.uint8)
    pts = _grid(120, 640, 60, 420, step=40)
    rays = np.hstack([cam0.undistort_points(pts), np.ones((len(pts), 1))])
    cfg = load_config("euroc-stereo-imu").frontend
    spread = {}
    for eps in (0.03, 0.001):
        matcher = StereoMatcher(calib, dataclasses.replace(cfg, stereo_klt_epsilon_px=eps))
        ends = []
        for believed_m in (depth_m * 0.97, depth_m * 1.03):
            m = matcher.match(left_u8, right_u8, pts, points_cam0_m=rays * believed_m)
            assert m.ok.all()
            np.testing.assert_allclose(m.points_cam0_m[:, 2], depth_m, rtol=0.01)
            ends.append(m.pixels_right[:, 0])
        spread[eps] = float(np.mean(ends[1] - ends[0]))
    assert abs(spread[0.03]) > 5e-4
    assert abs(spread[0.001]) < 2e-4

"""Sub-pixel corners: detected at half resolution (a 2-pixel lattice), refined with
cornerSubPix, they land on the true corners of a rendered checkerboard."""

from __future__ import annotations

import cv2
import numpy as np

from slam.config import FrontendConfig
from slam.frontend.features import detect_features

SUPERSAMPLE = 8


def _checkerboard(
    origin_px: tuple[float, float], square_px: float
) -> tuple[np.ndarray, np.ndarray]:
    """A 752x480 anti-aliased checkerboard (area-averaged from 8x supersampling) and its inner
    corners (x, y) in pixel coordinates (pixel centres at integers)."""
    h, w = 480, 752
    ys, xs = np.mgrid[0 : h * SUPERSAMPLE, 0 : w * SUPERSAMPLE]
    # sample positions in output pixel coordinates
    u = (xs + 0.5) / SUPERSAMPLE - 0.5
    v = (ys + 0.5) / SUPERSAMPLE - 0.5
    cell = np.floor((u - origin_px[0]) / square_px) + np.floor((v - origin_px[1]) / square_px)
    big = np.where(cell % 2 == 0, 200, 50).astype(np.float32)
    img = cv2.resize(big, (w, h), interpolation=cv2.INTER_AREA)
    cu = origin_px[0] + square_px * np.arange(-20, 40)
    cv = origin_px[1] + square_px * np.arange(-20, 40)
    cu, cv = cu[(cu > 10) & (cu < w - 10)], cv[(cv > 10) & (cv < h - 10)]
    corners = np.stack(np.meshgrid(cu, cv), axis=-1).reshape(-1, 2)
    return np.clip(img, 0, 255).astype(np.uint8), corners


def _errors(px: np.ndarray, truth: np.ndarray) -> np.ndarray:
    d = np.linalg.norm(px[:, None, :] - truth[None, :, :], axis=2)
    return d.min(axis=1)


def test_refined_corners_sit_on_the_true_corners() -> None:
    img, truth = _checkerboard((13.37, 21.71), 37.3)
    refined = detect_features(img, np.zeros((0, 2)), FrontendConfig())
    lattice = detect_features(img, np.zeros((0, 2)), FrontendConfig(corner_subpixel=False))
    assert len(refined) > 50 and len(lattice) > 50
    e_ref, e_lat = _errors(refined, truth), _errors(lattice, truth)
    assert np.median(e_ref) < 0.15, np.median(e_ref)  # measured 0.09
    assert np.median(e_lat) > 0.5, np.median(e_lat)  # the half-resolution lattice: 2.1
    # every refined corner belongs to a true corner (none dragged off by the larger window)
    assert np.percentile(e_ref, 95) < 0.3, np.percentile(e_ref, 95)


def test_a_zero_refinement_window_is_a_config_error(tmp_path) -> None:
    """cv2.cornerSubPix would fail deep in the front end's thread; the config says what to do."""
    import pytest

    from slam.config import load_config
    from slam.core.errors import SlamError

    bad = tmp_path / "bad.yaml"
    bad.write_text("preset: euroc-stereo-imu\nfrontend:\n  corner_subpixel_half_window_px: 0\n")
    with pytest.raises(SlamError, match="corner_subpixel: false"):
        load_config(str(bad))


def test_essential_ransac_recovers_a_motion_and_refuses_no_motion():
    """Five-point RANSAC on normalised matches: a translation's essential matrix satisfies the
    epipolar constraint on every match; identical points (no motion) give None, not an
    exception (OpenCV 5.1 raises there)."""
    from slam.frontend.features import essential_ransac

    rng = np.random.default_rng(0)
    pts = np.column_stack([rng.uniform(-1, 1, (60, 2)), rng.uniform(2, 5, 60)])
    x0 = pts[:, :2] / pts[:, 2:]
    moved = pts - np.array([0.2, 0.05, 0.0])
    x1 = moved[:, :2] / moved[:, 2:]
    found = essential_ransac(x0, x1, 1e-3)
    assert found is not None
    e, mask = found
    h0, h1 = np.hstack([x0, np.ones((60, 1))]), np.hstack([x1, np.ones((60, 1))])
    assert np.abs(np.einsum("ij,jk,ik->i", h1, e, h0)).max() < 1e-6
    assert mask.sum() == 60
    assert essential_ransac(x0, x0.copy(), 1e-3) is None

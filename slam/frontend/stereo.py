"""Left-right stereo matching on unrectified images: KLT along the epipolar line, then checks.

EuRoC-like rigs are not rectified, so matching works in the original images: each left feature
is KLT-tracked into the right image from a guess at a nominal depth, then kept only if it lies
within ``stereo_max_epipolar_px`` of its epipolar line, back-tracks to itself, and triangulates
in front of both cameras within the configured depth range.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from slam.config import FrontendConfig
from slam.core.calibration import Calibration
from slam.core.geometry import skew, transform_points
from slam.frontend.affine_klt import build_templates, refine_affine
from slam.frontend.features import (
    ReducedImages,
    brightness_ratio,
    match_brightness,
    track_klt,
)


@dataclass(frozen=True, eq=False)
class StereoMatches:
    """Stereo results for N left features (rows with ``ok`` False are invalid)."""

    ok: np.ndarray  # (N,) bool
    pixels_right: np.ndarray  # (N, 2) distorted right pixels
    points_cam0_m: np.ndarray  # (N, 3) triangulated points in the left camera frame


class StereoMatcher:
    """Matches left features into the right image and triangulates them."""

    def __init__(self, calib: Calibration, cfg: FrontendConfig, nominal_depth_m: float = 4.0):
        self.cfg = cfg
        self.cam0 = calib.cameras[0].intrinsics
        self.cam1 = calib.cameras[1].intrinsics
        c1_from_c0 = calib.cam1_from_cam0()
        self.r_10 = c1_from_c0[:3, :3]
        self.t_10 = c1_from_c0[:3, 3]
        self.cam1_from_cam0 = c1_from_c0
        self.essential = skew(self.t_10) @ self.r_10
        self.nominal_depth_m = nominal_depth_m
        self.proj0 = np.hstack([np.eye(3), np.zeros((3, 1))])
        self.proj1 = np.hstack([self.r_10, self.t_10[:, None]])

    def match(
        self,
        pyr_left: np.ndarray,
        pyr_right: np.ndarray,
        pixels_left: np.ndarray,
        points_cam0_m: np.ndarray | None = None,
        reduced: ReducedImages | None = None,
    ) -> StereoMatches:
        """Match ``pixels_left`` (N, 2) into the right image.

        ``points_cam0_m`` (N, 3, NaN rows where unknown): a known 3-D point per feature (a
        tracked landmark). Its projection is the KLT start in the right image, close enough for
        ``stereo_known_point_levels`` pyramid levels instead of the full pyramid that the
        nominal-depth guess needs, and a match must stay within ``stereo_known_max_shift_px`` of
        it instead of passing a backward track (together about half the stereo time).
        ``reduced``: the caller's cache for :func:`brightness_ratio`.
        """
        n = len(pixels_left)
        if n == 0:
            return StereoMatches(np.zeros(0, bool), np.zeros((0, 2)), np.zeros((0, 3)))
        norm0 = self.cam0.undistort_points(pixels_left)
        rays0 = np.hstack([norm0, np.ones((n, 1))])
        guess = self.cam1.project(
            transform_points(self.cam1_from_cam0, rays0 * self.nominal_depth_m)
        )
        known = np.zeros(n, dtype=bool)
        if points_cam0_m is not None:
            pts_c1 = transform_points(self.cam1_from_cam0, np.asarray(points_cam0_m, float))
            known = np.isfinite(pts_c1).all(axis=1) & (pts_c1[:, 2] > self.cfg.min_depth_m)
            if known.any():
                guess[known] = self.cam1.project(pts_c1[known])
        if self.cfg.klt_match_brightness:
            # the two cameras' gains differ (a few %): scale the brighter image down first
            # (around the left pixels in both images: the same ratio whatever the guesses, so
            # known points and the nominal-depth start match the same)
            ratio = brightness_ratio(pyr_left, pyr_right, pixels_left, pixels_left, reduced)
            pyr_left, pyr_right = match_brightness(pyr_left, pyr_right, ratio)
        px_right = np.zeros((n, 2), np.float32)
        ok = np.zeros(n, dtype=bool)
        if known.any():
            # The prediction replaces the backward check: a match must stay near it.
            px_right[known], ok[known] = track_klt(
                pyr_left,
                pyr_right,
                pixels_left[known],
                self.cfg,
                guess_to=guess[known],
                levels=self.cfg.stereo_known_point_levels,
                backward_check=False,
            )
            shift = np.linalg.norm(px_right[known] - guess[known], axis=1)
            ok[known] &= shift < self.cfg.stereo_known_max_shift_px
        if (~known).any():
            px_right[~known], ok[~known] = track_klt(
                pyr_left, pyr_right, pixels_left[~known], self.cfg, guess_to=guess[~known]
            )
        if self.cfg.stereo_affine_refine and ok.any():
            px_right[ok] = self._refine_affine(pyr_left, pyr_right, pixels_left[ok], px_right[ok])
        norm1 = self.cam1.undistort_points(px_right)
        rays1 = np.hstack([norm1, np.ones((n, 1))])
        # Epipolar distance of the right ray from the line E x0, in right-image pixels.
        lines = rays0 @ self.essential.T
        dist_norm = np.abs(np.sum(lines * rays1, axis=1)) / np.maximum(
            np.linalg.norm(lines[:, :2], axis=1), 1e-12
        )
        ok &= dist_norm * self.cam1.fx < self.cfg.stereo_max_epipolar_px
        pts4 = cv2.triangulatePoints(self.proj0, self.proj1, norm0.T, norm1.T)
        w = pts4[3]
        with np.errstate(divide="ignore", invalid="ignore"):
            pts = (pts4[:3] / w).T
        ok &= np.isfinite(pts).all(axis=1)
        pts = np.where(np.isfinite(pts), pts, 0.0)
        z0 = pts[:, 2]
        z1 = transform_points(self.cam1_from_cam0, pts)[:, 2]
        ok &= (
            (z0 > self.cfg.min_depth_m) & (z0 < self.cfg.max_depth_m) & (z1 > self.cfg.min_depth_m)
        )
        return StereoMatches(ok=ok, pixels_right=px_right.astype(np.float64), points_cam0_m=pts)

    def _refine_affine(
        self,
        image_left: np.ndarray,
        image_right: np.ndarray,
        pixels_left: np.ndarray,
        pixels_right: np.ndarray,
    ) -> np.ndarray:
        """The right pixels (N, 2) of KLT matches re-fitted with an affine warp of the left
        patch (``affine_klt.refine_affine``, gain and bias matched); a match whose fit fails
        keeps its KLT pixel.

        Why: on a surface seen at a grazing angle (a floor down a hall) the disparity changes
        across the KLT window, and a translation-only match lands on a gradient-weighted mean
        of it, 0.01-0.02 px off the centre's disparity; the map's scale hangs on disparities
        to a few thousandths of a pixel (BENCHMARKS.md, branch hall17)."""
        templates = build_templates(image_left, pixels_left, self.cfg.klt_window_px // 2)
        fit = refine_affine(templates, image_right, pixels_right, iterations=10, max_shift_px=0.5)
        out = np.array(pixels_right, dtype=np.float32, copy=True)
        out[fit.ok] = fit.pts_px[fit.ok]
        return out

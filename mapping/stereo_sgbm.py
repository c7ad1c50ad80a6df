"""Depth from the stereo pair by semi-global matching (OpenCV's StereoSGBM) after rectification.

The pair is rectified once per calibration (``cv2.stereoRectify`` or ``cv2.fisheye.stereoRectify``
with ``alpha = 0``: only valid pixels, so the rectified images have no black border), each
keyframe's images are remapped, SGBM gives a disparity (1/16 px, left-right checked, uniqueness
and speckle filtered) and ``depth = f B / disparity`` in the **rectified left camera**, whose
pinhole is :attr:`RectifiedStereo.K` and whose pose is ``world_from_cam0 @ cam0_from_rect``.

Why SGBM for the stereo partner: it matches along one image row with 8 (or 3) path smoothness
terms in optimised C++; the plane sweep's per-plane homography warps and box filters over the
same disparities cost 5-10x more (BENCHMARKS.md "Mapping") for a depth map no better on the
stereo pair. The sweep remains for views that are not a rectifiable pair (earlier keyframes).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from slam.core.calibration import CameraIntrinsics


@dataclass(frozen=True)
class SgbmConfig:
    """Parameters of :class:`RectifiedStereo` (OpenCV StereoSGBM's, in rectified pixels)."""

    min_depth_m: float = 0.4
    """Nearest depth searched: sets the disparity range f B / min_depth (rounded up to 16)."""
    block_size: int = 5
    """Matching window side (odd)."""
    mode: str = "sgbm3"
    """"sgbm3" (3-way: ~2x cheaper than 8 paths, slightly noisier) or "sgbm" (5 paths) or
    "hh" (full 8 paths, most memory)."""
    uniqueness_ratio: int = 10
    """Percent by which the best cost must beat the second best."""
    disp12_max_diff: int = 1
    """Left-right consistency tolerance (pixels); -1 disables the check."""
    speckle_window: int = 100
    """Remove disparity blobs smaller than this (pixels)..."""
    speckle_range: int = 2
    """...whose disparity differs from the surroundings by more than this (pixels)."""
    min_texture: float = 1.0
    """Drop pixels whose 7x7 grey-level standard deviation is below this (no texture). 3.0
    dropped the smooth parts of the suite's textures (sky, plain backgrounds: ~30 % of a
    room-loop image has a 7x7 deviation below 3, 13 % below 1) which SGBM's smoothness paths
    fill correctly between textured edges: room-loop with ground-truth poses, completion 87.7
    -> 97.0 % and mean vertex error 0.90 -> 0.83 cm at 1.0; 99.8 % and 0.95 cm at 0
    (BENCHMARKS.md, "Mapping", 2026-12-02 issue 20)."""
    scale: float = 1.0
    """Match at this fraction of the rectified image size (depth returned at that size)."""


def _dist(cam: CameraIntrinsics, n: int) -> np.ndarray:
    """Distortion coefficients padded to ``n`` (OpenCV wants 4 for fisheye, 4-14 otherwise)."""
    out = np.zeros(n)
    if cam.distortion_model != "none":
        d = np.asarray(cam.dist_coeffs, float).ravel()[:n]
        out[: len(d)] = d
    return out


_MODES = {
    "sgbm3": cv2.STEREO_SGBM_MODE_SGBM_3WAY,
    "sgbm": cv2.STEREO_SGBM_MODE_SGBM,
    "hh": cv2.STEREO_SGBM_MODE_HH,
}


class RectifiedStereo:
    """Rectify a calibrated stereo pair and compute depth in the rectified left camera."""

    def __init__(
        self,
        left: CameraIntrinsics,
        right: CameraIntrinsics,
        cam1_from_cam0: np.ndarray,
        config: SgbmConfig | None = None,
    ) -> None:
        self.config = cfg = config or SgbmConfig()
        if cfg.mode not in _MODES:
            raise ValueError(f"SGBM mode {cfg.mode!r}: use one of {sorted(_MODES)}")
        size = (left.width, left.height)
        rot = np.asarray(cam1_from_cam0[:3, :3], np.float64)
        trans = np.asarray(cam1_from_cam0[:3, 3], np.float64).reshape(3, 1)  # OpenCV 5: (3, 1)
        if left.distortion_model == "equidistant" and right.distortion_model == "equidistant":
            r1, r2, p1, p2, _ = cv2.fisheye.stereoRectify(
                left.K, _dist(left, 4), right.K, _dist(right, 4), size, rot, trans,
                flags=cv2.CALIB_ZERO_DISPARITY, newImageSize=size, balance=0.0,
            )  # fmt: skip
            init = cv2.fisheye.initUndistortRectifyMap
            n_dist = 4
        else:
            r1, r2, p1, p2, *_ = cv2.stereoRectify(
                left.K, _dist(left, 5), right.K, _dist(right, 5), size, rot, trans,
                flags=cv2.CALIB_ZERO_DISPARITY, alpha=0.0,
            )  # fmt: skip
            init = cv2.initUndistortRectifyMap
            n_dist = 5
        self._maps = [
            init(cam.K, _dist(cam, n_dist), r, p, size, cv2.CV_16SC2)
            for cam, r, p in ((left, r1, p1), (right, r2, p2))
        ]
        s = cfg.scale
        k = p1[:3, :3].copy()
        if s != 1.0:
            k[0, 0] *= s
            k[1, 1] *= s
            k[0, 2] = (k[0, 2] + 0.5) * s - 0.5
            k[1, 2] = (k[1, 2] + 0.5) * s - 0.5
        self.K = k
        """Pinhole of the rectified left camera at the matching scale."""
        self.baseline_m = float(-p2[0, 3] / p2[0, 0])
        cam0_from_rect = np.eye(4)
        cam0_from_rect[:3, :3] = r1.T  # r1 rotates cam0 points into the rectified frame
        self.cam0_from_rect = cam0_from_rect
        """Pose of the rectified left camera in cam0 (a rotation)."""
        fb = self.K[0, 0] * self.baseline_m
        n_disp = int(np.ceil(fb / cfg.min_depth_m / 16.0)) * 16
        self.num_disparities = max(16, n_disp)
        self._sgbm: cv2.StereoSGBM | None = None

    def __getstate__(self) -> dict:
        """Picklable (for the mapper's worker process): the matcher is rebuilt on use."""
        state = self.__dict__.copy()
        state["_sgbm"] = None
        return state

    def _matcher(self) -> cv2.StereoSGBM:
        if self._sgbm is not None:
            return self._sgbm
        cfg = self.config
        b = cfg.block_size
        self._sgbm = cv2.StereoSGBM_create(
            minDisparity=0,
            numDisparities=self.num_disparities,
            blockSize=b,
            P1=8 * b * b,
            P2=32 * b * b,
            disp12MaxDiff=cfg.disp12_max_diff,
            uniquenessRatio=cfg.uniqueness_ratio,
            speckleWindowSize=cfg.speckle_window,
            speckleRange=cfg.speckle_range,
            mode=_MODES[cfg.mode],
        )
        return self._sgbm

    def rectify(self, left: np.ndarray, right: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Rectified (left, right) images at the matching scale (any dtype/channels)."""
        out = []
        for img, (m1, m2) in zip((left, right), self._maps):
            r = cv2.remap(img, m1, m2, cv2.INTER_LINEAR)
            if self.config.scale != 1.0:
                r = cv2.resize(r, None, fx=self.config.scale, fy=self.config.scale,
                               interpolation=cv2.INTER_AREA)  # fmt: skip
            out.append(r)
        return out[0], out[1]

    def depth(
        self,
        left_rect_gray: np.ndarray,
        right_rect_gray: np.ndarray,
        min_depth_m: float | None = None,
    ) -> np.ndarray:
        """Depth (float32 m, 0 = invalid) in the rectified left camera from rectified uint8
        grey images. ``min_depth_m`` (above the configured one) narrows the disparity search
        for this pair (the cost is about linear in the number of disparities)."""
        matcher = self._matcher()
        n_disp = self.num_disparities
        if min_depth_m is not None and min_depth_m > self.config.min_depth_m:
            fb = self.K[0, 0] * self.baseline_m
            n_disp = min(n_disp, max(32, int(np.ceil(fb / min_depth_m / 16.0)) * 16))
        matcher.setNumDisparities(n_disp)
        disp = matcher.compute(left_rect_gray, right_rect_gray).astype(np.float32) / 16.0
        depth = np.zeros_like(disp)
        ok = disp > 0.5
        if self.config.min_texture > 0:
            img = left_rect_gray.astype(np.float32)
            mean = cv2.blur(img, (7, 7))
            var = cv2.blur(img * img, (7, 7)) - mean * mean
            ok &= var > self.config.min_texture**2
        depth[ok] = (self.K[0, 0] * self.baseline_m) / disp[ok]
        return depth

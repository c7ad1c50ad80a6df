"""Plane-sweep multi-view stereo: a depth map for a reference view from calibrated source views.

The classic derivation (Collins 1996; Gallup et al. 2007):

- hypotheses are fronto-parallel planes ``Z = z_i`` in the reference camera, sampled uniformly in
  inverse depth between ``depth_min_m`` and ``depth_max_m`` (uniform in disparity, so in pixels);
- a source view is warped onto the reference through the plane-induced homography
  ``H(Z) = K_src (R + t n^T / Z) K_ref^-1`` with ``n = (0, 0, 1)`` and ``[R | t] = src_from_ref``
  (``cv2.warpPerspective`` with ``WARP_INVERSE_MAP``; it releases the GIL);
- photo-consistency per pixel and plane is windowed ZNCC (box filters) or SAD, aggregated over
  the source views robustly to occlusion: the mean of the best ``k`` views;
- the best plane per pixel is tracked while sweeping (no cost volume is kept), refined below
  the plane spacing by a parabola through its two neighbours, and converted to depth;
- confidence is the peak ratio ``(1 - second) / (1 - best)`` of the best and the best
  non-adjacent ZNCC (cost ratio for SAD); unconfident, low-score and textureless pixels are
  dropped; :func:`depth_consistency` checks one depth map against another view's.

Images are undistorted first (:class:`Undistorter`, ``cv2.initUndistortRectifyMap``), so every
view is an ideal pinhole with matrix ``K``.
"""

from __future__ import annotations

from collections.abc import Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import cv2
import numpy as np

from slam.calibration import CameraIntrinsics

COSTS = ("zncc", "sad")


@dataclass(frozen=True)
class SweepConfig:
    """Parameters of :func:`plane_sweep`."""

    num_planes: int = 64
    """Number of fronto-parallel planes."""
    depth_min_m: float = 0.4
    """Nearest plane (m)."""
    depth_max_m: float = 10.0
    """Farthest plane (m)."""
    window: int = 7
    """Side of the square matching window (pixels, odd)."""
    cost: str = "zncc"
    """'zncc' (windowed zero-mean NCC, robust to gain and offset) or 'sad' (windowed mean
    absolute difference: about 2x cheaper, needs equal exposure)."""
    best_k: int | None = None
    """Views averaged per pixel and plane (the best ones); None = ceil(views / 2)."""
    min_peak_ratio: float = 1.15
    """Drop pixels whose best cost is not this much below the second best (ZNCC: 1 - score)."""
    min_score: float = 0.5
    """Drop pixels whose best ZNCC is below this (ignored for SAD)."""
    max_sad: float = 20.0
    """Drop pixels whose best mean absolute difference is above this (grey levels, SAD only)."""
    min_texture: float = 3.0
    """Drop pixels whose window standard deviation is below this (grey levels)."""
    speckle_max_px: int = 60
    """Remove connected blobs of valid pixels up to this size whose plane index differs from
    their surroundings by more than ``speckle_max_diff`` (cv2.filterSpeckles); 0 disables."""
    speckle_max_diff: float = 1.5
    """Plane-index step that separates speckle blobs from their neighbours."""
    threads: int = 1
    """Worker threads over plane chunks (OpenCV releases the GIL); results do not depend on it."""

    def __post_init__(self) -> None:
        if self.cost not in COSTS:
            raise ValueError(f"cost must be one of {COSTS}, got {self.cost!r}")
        if self.window % 2 != 1 or self.window < 3:
            raise ValueError("window must be odd and >= 3")
        if not 0 < self.depth_min_m < self.depth_max_m:
            raise ValueError("need 0 < depth_min_m < depth_max_m")


@dataclass(frozen=True, eq=False)
class SourceView:
    """A source image (undistorted, grey or RGB), its pinhole K and the rigid src_from_ref."""

    image: np.ndarray
    K: np.ndarray
    src_from_ref: np.ndarray


@dataclass(frozen=True, eq=False)
class DepthResult:
    """Output of a sweep: depth (m, 0 where filtered out) and per-pixel diagnostics."""

    depth_m: np.ndarray  # (H, W) float32, 0 = invalid
    raw_depth_m: np.ndarray  # (H, W) float32 before filtering
    score: np.ndarray  # (H, W) float32 best aggregated ZNCC (or -mean abs difference for SAD)
    peak_ratio: np.ndarray  # (H, W) float32 confidence
    textured: np.ndarray  # (H, W) bool window std >= min_texture

    @property
    def valid(self) -> np.ndarray:
        return self.depth_m > 0


class Undistorter:
    """Undistort images of one camera to an ideal pinhole with the same size.

    The new K keeps the calibrated focal lengths and principal point (no cropping decisions), so
    depth maps are in a pinhole camera with matrix :attr:`K`.
    """

    def __init__(self, intrinsics: CameraIntrinsics) -> None:
        self.intrinsics = intrinsics
        self.K = intrinsics.K.copy()
        size = (intrinsics.width, intrinsics.height)
        self._maps: tuple[np.ndarray, np.ndarray] | None
        if intrinsics.distortion_model == "none" or not any(intrinsics.distortion):
            self._maps = None
        elif intrinsics.distortion_model == "equidistant":
            self._maps = cv2.fisheye.initUndistortRectifyMap(
                intrinsics.K, intrinsics.dist_coeffs, np.eye(3), self.K, size, cv2.CV_16SC2
            )
        else:
            self._maps = cv2.initUndistortRectifyMap(
                intrinsics.K, intrinsics.dist_coeffs, np.eye(3), self.K, size, cv2.CV_16SC2
            )

    def __call__(self, image: np.ndarray, interpolation: int = cv2.INTER_LINEAR) -> np.ndarray:
        """Undistorted image (``cv2.INTER_NEAREST`` for depth maps and labels)."""
        if self._maps is None:
            return image
        return cv2.remap(image, self._maps[0], self._maps[1], interpolation)


def to_gray_f32(image: np.ndarray) -> np.ndarray:
    """uint8/float grey or RGB -> float32 grey (0..255 scale kept)."""
    img = np.asarray(image)
    if img.ndim == 3:
        img = cv2.cvtColor(img, cv2.COLOR_RGB2GRAY)
    return img.astype(np.float32, copy=False)


def inverse_depth_planes(config: SweepConfig) -> np.ndarray:
    """Plane depths (m), near to far, uniform in inverse depth."""
    inv = np.linspace(1.0 / config.depth_min_m, 1.0 / config.depth_max_m, config.num_planes)
    return 1.0 / inv


def plane_homography(
    K_ref: np.ndarray, K_src: np.ndarray, src_from_ref: np.ndarray, depth_m: float
) -> np.ndarray:
    """Homography taking reference pixels to source pixels for the plane Z_ref = depth_m."""
    rot = src_from_ref[:3, :3]
    t = src_from_ref[:3, 3:4]
    n = np.array([[0.0, 0.0, 1.0]])
    return K_src @ (rot + t @ n / depth_m) @ np.linalg.inv(K_ref)


def _box(img: np.ndarray, win: int) -> np.ndarray:
    """Window mean (separable box filter: cheaper than cv2.boxFilter here)."""
    k = np.full(win, 1.0 / win, np.float32)
    return cv2.sepFilter2D(img, cv2.CV_32F, k, k, borderType=cv2.BORDER_REFLECT)


class _RefStats:
    """Window statistics of the reference image, computed once per sweep."""

    def __init__(self, ref: np.ndarray, win: int) -> None:
        self.img = ref
        self.mean = _box(ref, win)
        var = _box(ref * ref, win) - self.mean * self.mean
        self.std = np.sqrt(np.maximum(var, 0.0))
        self.inv_std = 1.0 / np.maximum(self.std, 1e-3)


def _score_zncc(ref: _RefStats, warped: np.ndarray, win: int) -> np.ndarray:
    """Windowed ZNCC in [-1, 1]; pixels whose window leaves the source image get -1."""
    mu_s = _box(warped, win)
    mu_ss = _box(cv2.multiply(warped, warped), win)
    mu_rs = _box(cv2.multiply(ref.img, warped), win)
    cov = cv2.subtract(mu_rs, cv2.multiply(ref.mean, mu_s))
    var_s = cv2.subtract(mu_ss, cv2.multiply(mu_s, mu_s))
    inv_std_s = cv2.pow(cv2.max(var_s, 1e-2), -0.5)
    score = cv2.multiply(cv2.multiply(cov, inv_std_s), ref.inv_std)
    cv2.patchNaNs(score, -1.0)  # NaN = outside the source image
    return score


def _score_sad(ref: _RefStats, warped: np.ndarray, win: int) -> np.ndarray:
    """Negated windowed mean absolute difference (higher is better); outside = -255."""
    score = -_box(cv2.absdiff(ref.img, warped), win)
    cv2.patchNaNs(score, -255.0)
    return score


def _aggregate(scores: list[np.ndarray], k: int) -> np.ndarray:
    """Mean of the best k view scores per pixel (robust to occlusion in the other views)."""
    if len(scores) == 1:
        return scores[0]
    if k == 1:
        out = scores[0]
        for s in scores[1:]:
            out = cv2.max(out, s)
        return out
    if k >= len(scores):
        return np.asarray(np.mean(scores, axis=0, dtype=np.float32))
    stack = np.stack(scores)
    part = np.partition(stack, len(scores) - k, axis=0)[len(scores) - k :]
    return np.asarray(part.mean(axis=0, dtype=np.float32))


def plane_sweep(
    ref_image: np.ndarray,
    K_ref: np.ndarray,
    sources: Sequence[SourceView],
    config: SweepConfig | None = None,
) -> DepthResult:
    """Depth map of the reference view (see the module docstring). Images must be undistorted."""
    cfg = config or SweepConfig()
    if not sources:
        raise ValueError("plane_sweep needs at least one source view")
    win = cfg.window
    ref = _RefStats(to_gray_f32(ref_image), win)
    h, w = ref.img.shape
    srcs = [to_gray_f32(s.image) for s in sources]
    k = cfg.best_k or (len(sources) + 1) // 2
    depths = inverse_depth_planes(cfg)
    flags = cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP

    n_planes = len(depths)
    volume = np.empty((n_planes, h, w), np.float32)  # aggregated score per plane

    def sweep_chunk(plane_ids: range) -> tuple[np.ndarray, np.ndarray]:
        best = np.full((h, w), -np.inf, np.float32)
        best_i = np.zeros((h, w), np.int32)
        for i in plane_ids:
            view_scores = []
            for src, view in zip(srcs, sources):
                hom = plane_homography(K_ref, view.K, view.src_from_ref, float(depths[i]))
                warped = cv2.warpPerspective(
                    src,
                    hom,
                    (w, h),
                    flags=flags,
                    borderMode=cv2.BORDER_CONSTANT,
                    borderValue=np.nan,
                )
                if cfg.cost == "zncc":
                    view_scores.append(_score_zncc(ref, warped, win))
                else:
                    view_scores.append(_score_sad(ref, warped, win))
            s = _aggregate(view_scores, k)
            volume[i] = s
            np.copyto(best_i, np.int32(i), where=s > best)
            cv2.max(best, s, dst=best)
        return best, best_i

    n_threads = max(1, min(cfg.threads, n_planes))
    bounds = np.linspace(0, n_planes, n_threads + 1).astype(int)
    chunks = [range(bounds[j], bounds[j + 1]) for j in range(n_threads)]
    if n_threads == 1:
        results = [sweep_chunk(chunks[0])]
    else:  # OpenCV and numpy release the GIL: plane chunks run truly in parallel
        with ThreadPoolExecutor(n_threads) as pool:
            results = list(pool.map(sweep_chunk, chunks))
    best, best_i = results[0]
    for b_j, i_j in results[1:]:  # later chunks win only when strictly better
        np.copyto(best_i, i_j, where=b_j > best)
        np.maximum(best, b_j, out=best)

    # Scores at the neighbouring planes (-inf beyond the ends), then the best non-adjacent one.
    idx = best_i[None]
    best_prev = np.take_along_axis(volume, np.maximum(idx - 1, 0), 0)[0]
    best_next = np.take_along_axis(volume, np.minimum(idx + 1, n_planes - 1), 0)[0]
    best_prev[best_i == 0] = -np.inf
    best_next[best_i == n_planes - 1] = -np.inf
    for d in (-1, 0, 1):
        np.put_along_axis(volume, np.clip(idx + d, 0, n_planes - 1), -np.inf, 0)
    second = volume.max(axis=0)

    # Parabola through (i-1, i, i+1); a missing neighbour (edge plane) means no refinement.
    denom = best_prev - 2.0 * best + best_next
    with np.errstate(invalid="ignore"):
        ok = np.isfinite(denom) & (denom < -1e-6)
        offset = np.where(ok, 0.5 * (best_prev - best_next) / np.where(ok, denom, -1.0), 0.0)
    offset = np.clip(offset, -0.5, 0.5)
    inv0, inv1 = 1.0 / cfg.depth_min_m, 1.0 / cfg.depth_max_m
    step = (inv1 - inv0) / max(cfg.num_planes - 1, 1)
    inv_depth = inv0 + (best_i + offset) * step
    raw_depth = (1.0 / inv_depth).astype(np.float32)

    if cfg.cost != "sad":
        c1 = 1.0 - best
        c2 = np.where(np.isfinite(second), 1.0 - second, 2.0)
        good_score = best >= cfg.min_score
    else:
        c1 = -best
        c2 = np.where(np.isfinite(second), -second, 255.0)
        good_score = c1 <= cfg.max_sad
    peak_ratio = (c2 / np.maximum(c1, 1e-3)).astype(np.float32)
    textured = ref.std >= cfg.min_texture
    keep = textured & good_score & (peak_ratio >= cfg.min_peak_ratio) & ok
    if cfg.speckle_max_px > 0:
        # Plane index (1-based, x16 fixed point) as a disparity image for filterSpeckles.
        disp = np.where(keep, np.round((best_i + offset + 1.0) * 16.0), 0).astype(np.int16)
        cv2.filterSpeckles(disp, 0, cfg.speckle_max_px, int(round(cfg.speckle_max_diff * 16)))
        keep &= disp > 0
    depth = np.where(keep, raw_depth, 0.0).astype(np.float32)
    return DepthResult(depth, raw_depth, best, peak_ratio, textured)


def depth_consistency(
    depth_ref_m: np.ndarray,
    K_ref: np.ndarray,
    depth_other_m: np.ndarray,
    K_other: np.ndarray,
    other_from_ref: np.ndarray,
    rel_tol: float = 0.01,
) -> tuple[np.ndarray, np.ndarray]:
    """Check a depth map against another view's depth map.

    Every valid reference pixel is back-projected, moved into the other camera and projected;
    it agrees when the other depth map at that pixel is within ``rel_tol`` (relative) of the
    point's depth there. Returns (agree mask, checked mask): checked = the point lands on a
    valid pixel of the other map; pixels that cannot be checked are neither agreeing nor not.
    """
    h, w = depth_ref_m.shape
    v, u = np.nonzero(depth_ref_m > 0)
    z = depth_ref_m[v, u].astype(np.float64)
    pts = np.stack([(u - K_ref[0, 2]) / K_ref[0, 0] * z, (v - K_ref[1, 2]) / K_ref[1, 1] * z, z], 1)
    p_o = pts @ other_from_ref[:3, :3].T + other_from_ref[:3, 3]
    zo = p_o[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        uo = np.round(K_other[0, 0] * p_o[:, 0] / zo + K_other[0, 2]).astype(np.int64)
        vo = np.round(K_other[1, 1] * p_o[:, 1] / zo + K_other[1, 2]).astype(np.int64)
    ho, wo = depth_other_m.shape
    inside = (zo > 0) & (uo >= 0) & (uo < wo) & (vo >= 0) & (vo < ho)
    d_other = np.zeros_like(zo)
    d_other[inside] = depth_other_m[vo[inside], uo[inside]]
    checked_pts = inside & (d_other > 0)
    agree_pts = checked_pts & (np.abs(d_other - zo) <= rel_tol * zo)
    agree = np.zeros((h, w), bool)
    checked = np.zeros((h, w), bool)
    agree[v, u] = agree_pts
    checked[v, u] = checked_pts
    return agree, checked

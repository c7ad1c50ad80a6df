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

from slam.core.calibration import CameraIntrinsics

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


_STRIP_ROWS = 48
"""Reference rows per work unit: the sweep runs strip by strip (all planes for one strip, then
the next), so its dozen temporaries stay in the L2 cache; threads take whole strips. The strip
layout does not depend on the thread count, so neither do the results."""


def _box_kernel(win: int) -> np.ndarray:
    return np.full(win, 1.0 / win, np.float32)


def _box(img: np.ndarray, win: int, dst: np.ndarray | None = None) -> np.ndarray:
    """Window mean (separable box filter: cheaper than cv2.boxFilter here)."""
    k = _box_kernel(win)
    return cv2.sepFilter2D(img, cv2.CV_32F, k, k, dst=dst, borderType=cv2.BORDER_REFLECT)


class _RefStats:
    """Window statistics of the reference image, computed once per sweep."""

    def __init__(self, ref: np.ndarray, win: int) -> None:
        self.img = np.ascontiguousarray(ref, np.float32)
        self.mean = _box(self.img, win)
        var = _box(self.img * self.img, win) - self.mean * self.mean
        self.std = np.sqrt(np.maximum(var, 0.0))
        self.inv_std = (1.0 / np.maximum(self.std, 1e-3)).astype(np.float32)
        self.neg_mean_inv_std = (-self.mean * self.inv_std).astype(np.float32)
        r = win // 2  # rows reflected above and below, as the box filter's border does
        self.img_padded = cv2.copyMakeBorder(self.img, r, r, 0, 0, cv2.BORDER_REFLECT)


class _StripSweep:
    """Sweep of all planes over one strip of reference rows with preallocated buffers.

    The buffers hold the strip's rows plus ``r = window // 2`` halo rows on each side (reflected
    at the image's top and bottom, as the full-image box filter would), so the box filters of
    the core rows see exactly what they would see on the full image. The three images whose
    window means ZNCC needs (I_s, I_s^2, I_r I_s, all warped) are stacked in one tall buffer and
    box-filtered by ONE call (a quarter cheaper than three; the rows where the stacked images
    meet are halo rows, never used). Every OpenCV call writes into a buffer (``dst=``).
    """

    def __init__(
        self,
        ref: _RefStats,
        srcs: list[np.ndarray],
        homs: np.ndarray,
        cfg: SweepConfig,
        k: int,
        rows: tuple[int, int],
    ) -> None:
        h, w = ref.img.shape
        self.r = r = cfg.window // 2
        self.y0, self.y1 = rows
        self.top, self.bottom = self.y0 == 0, self.y1 == h
        c = self.y1 - self.y0
        self.n = n = c + 2 * r
        self.w = w
        self.ref, self.srcs, self.cfg, self.k = ref, srcs, cfg, k
        self.kernel = _box_kernel(cfg.window)
        # Strip homographies: buffer row y is reference row y + y0 - r.
        self.homs = homs.copy()
        self.homs[..., :, 2] += (self.y0 - r) * homs[..., :, 1]
        self.stack = np.empty((3 * n, w), np.float32)
        self.boxed = np.empty((3 * n, w), np.float32)
        self.warped, self.squared, self.product = (
            self.stack[j * n : (j + 1) * n] for j in range(3)
        )
        self.mu_s_c, self.mu_ss_c, self.mu_rs_c = (
            self.boxed[j * n + r : j * n + r + c] for j in range(3)
        )
        self.view_scores = [np.empty((c, w), np.float32) for _ in srcs]
        self.tmp_c = np.empty((c, w), np.float32)
        self.ref_img = ref.img_padded[self.y0 : self.y1 + 2 * r]
        self.ref_inv_std = ref.inv_std[self.y0 : self.y1]
        self.ref_neg_mean_inv_std = ref.neg_mean_inv_std[self.y0 : self.y1]

    def _box(self, src: np.ndarray, dst: np.ndarray) -> None:
        cv2.sepFilter2D(
            src, cv2.CV_32F, self.kernel, self.kernel, dst=dst, borderType=cv2.BORDER_REFLECT
        )

    def _warp(self, view: int, plane: int) -> None:
        warped, r = self.warped, self.r
        cv2.warpPerspective(
            self.srcs[view],
            self.homs[view, plane],
            (self.w, self.n),
            dst=warped,
            flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
            borderMode=cv2.BORDER_CONSTANT,
            borderValue=np.nan,
        )
        if self.top:  # reflect like cv2.BORDER_REFLECT: row -1 = row 0
            warped[:r] = warped[r : 2 * r][::-1]
        if self.bottom:
            e = self.n - r
            warped[e:] = warped[e - r : e][::-1]

    def _score_zncc(self, out: np.ndarray) -> None:
        """Windowed ZNCC in [-1, 1] of the warped source; windows leaving the source get -1.

        ``zncc = (box(I_r I_s) - mu_r mu_s) / (sigma_r sigma_s)``, evaluated as
        ``(box(I_r I_s) / sigma_r - (mu_r / sigma_r) mu_s) / sigma_s`` on the core rows.
        """
        cv2.multiply(self.warped, self.warped, dst=self.squared)
        cv2.multiply(self.ref_img, self.warped, dst=self.product)
        self._box(self.stack, self.boxed)
        mu_s, mu_ss, mu_rs, tmp_c = self.mu_s_c, self.mu_ss_c, self.mu_rs_c, self.tmp_c
        cv2.multiply(mu_rs, self.ref_inv_std, dst=mu_rs)
        cv2.accumulateProduct(self.ref_neg_mean_inv_std, mu_s, mu_rs)  # cov / sigma_r
        cv2.multiply(mu_s, mu_s, dst=tmp_c)
        cv2.subtract(mu_ss, tmp_c, dst=mu_ss)  # var_s
        cv2.max(mu_ss, 1e-2, dst=mu_ss)
        cv2.pow(mu_ss, -0.5, dst=mu_ss)
        cv2.multiply(mu_rs, mu_ss, dst=out)
        cv2.patchNaNs(out, -1.0)  # NaN = outside the source image

    def _score_sad(self, out: np.ndarray) -> None:
        """Negated windowed mean absolute difference (higher is better); outside = -255."""
        n = self.n
        cv2.absdiff(self.ref_img, self.warped, dst=self.squared)
        self._box(self.squared, self.boxed[n : 2 * n])
        np.negative(self.mu_ss_c, out=out)
        cv2.patchNaNs(out, -255.0)

    def _aggregate(self, out: np.ndarray) -> None:
        """Mean of the best k view scores per pixel (robust to occlusion in the other views)."""
        scores, k, n = self.view_scores, self.k, len(self.view_scores)
        if n == 1:
            np.copyto(out, scores[0])
        elif k == 1:
            cv2.max(scores[0], scores[1], dst=out)
            for s in scores[2:]:
                cv2.max(out, s, dst=out)
        elif k >= n or k == n - 1:
            np.copyto(out, scores[0])
            for s in scores[1:]:
                cv2.add(out, s, dst=out)
            if k < n:  # drop the worst view
                np.copyto(self.tmp_c, scores[0])
                for s in scores[1:]:
                    cv2.min(self.tmp_c, s, dst=self.tmp_c)
                cv2.subtract(out, self.tmp_c, dst=out)
            np.multiply(out, np.float32(1.0 / min(k, n)), out=out)
        else:
            part = np.partition(np.stack(scores), n - k, axis=0)[n - k :]
            np.mean(part, axis=0, dtype=np.float32, out=out)

    def run(self, planes: int) -> tuple[np.ndarray, ...]:
        """Best score, its plane index, the scores of its two neighbour planes (-inf beyond the
        ends) and the best score of a non-adjacent plane, for the core rows."""
        c, w = self.y1 - self.y0, self.w
        volume = np.empty((planes, c, w), np.float32)  # aggregated score per plane
        best = np.empty((c, w), np.float32)
        best_i = np.zeros((c, w), np.float32)
        score = self._score_zncc if self.cfg.cost == "zncc" else self._score_sad
        for i in range(planes):
            for v in range(len(self.srcs)):
                self._warp(v, i)
                score(self.view_scores[v])
            s = volume[i]
            self._aggregate(s)
            if i == 0:
                np.copyto(best, s)
                continue
            # Planes come in increasing order, so best_i = max(best_i, i where s > best).
            cv2.subtract(s, best, dst=self.tmp_c)
            cv2.threshold(self.tmp_c, 0.0, float(i), cv2.THRESH_BINARY, dst=self.tmp_c)
            cv2.max(best_i, self.tmp_c, dst=best_i)
            cv2.max(best, s, dst=best)

        idx = best_i.astype(np.intp).ravel()
        lin = idx * (c * w) + np.arange(c * w)
        flat = volume.reshape(-1)
        has_prev, has_next = idx > 0, idx < planes - 1
        prev = np.where(has_prev, flat[np.where(has_prev, lin - c * w, lin)], -np.inf)
        nxt = np.where(has_next, flat[np.where(has_next, lin + c * w, lin)], -np.inf)
        flat[lin] = -np.inf
        flat[lin[has_prev] - c * w] = -np.inf
        flat[lin[has_next] + c * w] = -np.inf
        second = volume.max(axis=0) if planes > 0 else np.full((c, w), -np.inf, np.float32)
        return (
            best,
            best_i.astype(np.int32),
            prev.reshape(c, w).astype(np.float32),
            nxt.reshape(c, w).astype(np.float32),
            second,
        )


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
    ref = _RefStats(to_gray_f32(ref_image), cfg.window)
    h, w = ref.img.shape
    if min(h, w) < cfg.window:
        raise ValueError(f"image {w}x{h} is smaller than the {cfg.window}-pixel window")
    srcs = [np.ascontiguousarray(to_gray_f32(s.image)) for s in sources]
    k = cfg.best_k or (len(sources) + 1) // 2
    depths = inverse_depth_planes(cfg)
    n_planes = len(depths)
    # H(Z) = K_s R K_ref^-1 + (K_s t n^T K_ref^-1) / Z for every view and plane.
    k_ref_inv = np.linalg.inv(K_ref)
    n_row = np.array([[0.0, 0.0, 1.0]])
    homs = np.array(
        [
            (v.K @ v.src_from_ref[:3, :3] @ k_ref_inv)[None]
            + (v.K @ v.src_from_ref[:3, 3:4] @ n_row @ k_ref_inv)[None] / depths[:, None, None]
            for v in sources
        ]
    )

    best = np.empty((h, w), np.float32)
    best_i = np.empty((h, w), np.int32)
    best_prev = np.empty((h, w), np.float32)
    best_next = np.empty((h, w), np.float32)
    second = np.empty((h, w), np.float32)

    # Strips of about _STRIP_ROWS rows (fixed by the image height, not by the thread count).
    n_strips = max(1, round(h / _STRIP_ROWS))
    bounds = np.linspace(0, h, n_strips + 1).round().astype(int)

    def sweep_strip(j: int) -> None:
        y0, y1 = int(bounds[j]), int(bounds[j + 1])
        out = _StripSweep(ref, srcs, homs, cfg, k, (y0, y1)).run(n_planes)
        for dst, part in zip((best, best_i, best_prev, best_next, second), out):
            dst[y0:y1] = part

    n_threads = max(1, min(cfg.threads, n_strips))
    if n_threads == 1:
        for j in range(n_strips):
            sweep_strip(j)
    else:  # OpenCV and numpy release the GIL: strips run truly in parallel
        with ThreadPoolExecutor(n_threads) as pool:
            list(pool.map(sweep_strip, range(n_strips)))

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

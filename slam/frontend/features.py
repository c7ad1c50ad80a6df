"""Feature detection with grid bucketing, and pyramidal KLT with a forward-backward check."""

from __future__ import annotations

import cv2
import numpy as np

from slam.config import FrontendConfig

_SUBPIX_CRITERIA = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 10, 0.01)


def detect_features(
    image: np.ndarray,
    existing_px: np.ndarray,
    cfg: FrontendConfig,
) -> np.ndarray:
    """New corners (M, 2) in grid cells that are short of features.

    Every cell of a ``grid_rows x grid_cols`` grid is topped up to its share of
    ``max_features``; a mask keeps new corners ``min_feature_distance_px`` from existing ones.
    Shi-Tomasi runs on the half-resolution image (measured 1 ms instead of 3.6 ms on 752x480,
    at keyframes, on the front end's critical path): KLT then tracks the patch around each
    point at full resolution, so detection precision does not limit tracking precision.
    """
    h, w = image.shape[:2]
    n_cells = cfg.grid_rows * cfg.grid_cols
    per_cell = max(1, int(np.ceil(cfg.max_features / n_cells)))
    if len(existing_px) >= cfg.max_features:
        return np.zeros((0, 2), dtype=np.float32)
    half = cv2.pyrDown(image)
    mask = np.full(half.shape[:2], 255, dtype=np.uint8)
    counts = np.zeros(n_cells, dtype=np.int64)
    radius = max(1, cfg.min_feature_distance_px // 2)
    if len(existing_px):
        for x, y in (existing_px * 0.5).astype(int):
            cv2.circle(mask, (int(x), int(y)), radius, 0, -1)
        counts += np.bincount(_cells(existing_px, w, h, cfg), minlength=n_cells)
    corners = cv2.goodFeaturesToTrack(
        half,
        maxCorners=cfg.max_features * 4,
        qualityLevel=cfg.corner_quality,
        minDistance=radius,
        mask=mask,
        blockSize=3,
    )
    if corners is None:
        return np.zeros((0, 2), dtype=np.float32)
    corners = corners.reshape(-1, 2) * 2.0 + 0.5  # pyrDown pixel centres -> full resolution
    corners[:, 0] = np.clip(corners[:, 0], 0, w - 1)
    corners[:, 1] = np.clip(corners[:, 1], 0, h - 1)
    # Bucketing, strongest first (goodFeaturesToTrack sorts by response): rank of each corner
    # within its cell, kept while the cell is below its share.
    cell = _cells(corners, w, h, cfg)
    order = np.argsort(cell, kind="stable")
    sorted_cells = cell[order]
    first = np.searchsorted(sorted_cells, sorted_cells, side="left")
    rank = np.empty(len(cell), dtype=np.int64)
    rank[order] = np.arange(len(cell)) - first
    keep = rank < per_cell - counts[cell]
    budget = cfg.max_features - len(existing_px)
    kept = np.ascontiguousarray(corners[keep][:budget], dtype=np.float32)
    if cfg.corner_subpixel and len(kept):
        # only the kept corners: refining all of goodFeaturesToTrack's (4x as many, the weak
        # ones slow to converge) cost 8 ms per full detection with a 15-px window
        half_win = cfg.corner_subpixel_half_window_px
        cv2.cornerSubPix(image, kept, (half_win, half_win), (-1, -1), _SUBPIX_CRITERIA)
        kept[:, 0] = np.clip(kept[:, 0], 0, w - 1)
        kept[:, 1] = np.clip(kept[:, 1], 0, h - 1)
    return kept


def _cells(px: np.ndarray, w: int, h: int, cfg: FrontendConfig) -> np.ndarray:
    cx = np.clip((px[:, 0] * cfg.grid_cols / w).astype(int), 0, cfg.grid_cols - 1)
    cy = np.clip((px[:, 1] * cfg.grid_rows / h).astype(int), 0, cfg.grid_rows - 1)
    return cy * cfg.grid_cols + cx


def build_pyramid(image: np.ndarray, cfg: FrontendConfig) -> np.ndarray:
    """The KLT input for an image.

    OpenCV 5's Python binding no longer accepts a prebuilt pyramid in calcOpticalFlowPyrLK, so
    this returns the image itself and KLT builds its pyramid internally (measured ~0.3 ms).
    """
    return image


def reduced_image(image: np.ndarray) -> np.ndarray:
    """``image`` reduced 8x by area averaging, float32 (:func:`brightness_ratio`'s local means)."""
    h, w = image.shape[:2]
    small = cv2.resize(image, (max(w // 8, 1), max(h // 8, 1)), interpolation=cv2.INTER_AREA)
    return small.astype(np.float32)


class ReducedImages:
    """The :func:`reduced_image` of the last few images asked for, by identity: a frame's
    image is compared with the previous frame's, then with its stereo partner at a keyframe,
    then with the next frame's; each is reduced once instead of at every comparison."""

    def __init__(self, size: int = 3) -> None:
        self.size = size
        self._items: list[tuple[np.ndarray, np.ndarray]] = []

    def get(self, image: np.ndarray) -> np.ndarray:
        for img, small in self._items:
            if img is image:
                return small
        small = reduced_image(image)
        self._items = [*self._items[-(self.size - 1) :], (image, small)] if self.size > 1 else []
        return small


def brightness_ratio(
    image_from: np.ndarray,
    image_to: np.ndarray,
    px_from: np.ndarray,
    px_to: np.ndarray,
    reduced: ReducedImages | None = None,
) -> float:
    """How much brighter ``image_to`` is than ``image_from`` around corresponding points
    ``px_from`` / ``px_to`` (N, 2): the median ratio of their local mean intensities (1 with
    fewer than 8 points). The means are taken on 8x-reduced images (a 0.1 ms box filter), so
    a few pixels of error in ``px_to`` (a predicted position) do not matter. ``reduced``: a
    cache of those reduced images.

    Why: pyramidal KLT assumes constant brightness. An auto-exposure gain step (3 dB) between
    two frames moved its tracks by 0.5 px (median) and lost 16 % of them on a textured image;
    a 3 % stereo gain mismatch biased left-right matches. The caller scales the brighter image
    down by this ratio first (:func:`match_brightness`)."""
    n = min(len(px_from), len(px_to))
    if n < 8:
        return 1.0
    means = []
    for image, px in ((image_from, px_from[:n]), (image_to, px_to[:n])):
        small = reduced_image(image) if reduced is None else reduced.get(image)
        xy = np.asarray(px, np.float32) / 8.0 - 0.5
        means.append(
            cv2.remap(
                small,
                np.ascontiguousarray(xy[:, 0:1]),
                np.ascontiguousarray(xy[:, 1:2]),
                interpolation=cv2.INTER_LINEAR,
                borderMode=cv2.BORDER_REPLICATE,
            ).ravel()
        )
    good = (means[0] > 8.0) & (means[1] > 8.0) & (means[0] < 250.0) & (means[1] < 250.0)
    if good.sum() < 8:
        return 1.0
    return float(np.median(means[1][good] / means[0][good]))


def match_brightness(
    image_a: np.ndarray, image_b: np.ndarray, ratio_b_over_a: float, tolerance: float = 0.01
) -> tuple[np.ndarray, np.ndarray]:
    """``image_a`` and ``image_b`` with the brighter one scaled down by ``ratio_b_over_a``
    (:func:`brightness_ratio`), so that neither saturates; as they are when the ratio is
    within ``tolerance`` of 1."""
    if abs(np.log(max(ratio_b_over_a, 1e-6))) <= tolerance:
        return image_a, image_b
    if ratio_b_over_a > 1.0:
        return image_a, cv2.convertScaleAbs(image_b, alpha=1.0 / ratio_b_over_a)
    return cv2.convertScaleAbs(image_a, alpha=ratio_b_over_a), image_b


def track_klt(
    pyr_from: np.ndarray,
    pyr_to: np.ndarray,
    pts_from: np.ndarray,
    cfg: FrontendConfig,
    guess_to: np.ndarray | None = None,
    levels: int | None = None,
    backward_check: bool = True,
) -> tuple[np.ndarray, np.ndarray]:
    """Track points between two pyramids with a forward-backward consistency check.

    ``levels``: pyramid levels above the base image (default ``cfg.klt_pyramid_levels``); fewer
    will do when ``guess_to`` is already within a few pixels. ``backward_check=False`` skips
    the backward track (for callers that check the result another way).
    Returns ``(pts_to (N, 2) float32, ok (N,) bool)``.
    """
    n = len(pts_from)
    if n == 0:
        return np.zeros((0, 2), np.float32), np.zeros(0, bool)
    p0 = np.ascontiguousarray(pts_from, dtype=np.float32).reshape(-1, 1, 2)
    win = (cfg.klt_window_px, cfg.klt_window_px)
    max_level = cfg.klt_pyramid_levels if levels is None else levels
    # 20 iterations to 0.03 px: the same tracks as 30 to 0.01 px (median 2e-4 px apart), ~10% faster
    criteria = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 20, 0.03)
    flags = 0
    p1_init = None
    if guess_to is not None:
        p1_init = np.ascontiguousarray(guess_to, dtype=np.float32).reshape(-1, 1, 2).copy()
        flags = cv2.OPTFLOW_USE_INITIAL_FLOW
    p1, st1, _ = cv2.calcOpticalFlowPyrLK(
        pyr_from,
        pyr_to,
        p0,
        p1_init,
        winSize=win,
        maxLevel=max_level,
        criteria=criteria,
        flags=flags,
    )
    h, w = pyr_to.shape[:2]
    pts = p1.reshape(-1, 2)
    inside = (pts[:, 0] >= 0) & (pts[:, 0] < w - 1) & (pts[:, 1] >= 0) & (pts[:, 1] < h - 1)
    ok = (st1.ravel() == 1) & inside
    if not backward_check:
        return pts.astype(np.float32), ok
    p0_back, st2, _ = cv2.calcOpticalFlowPyrLK(
        pyr_to,
        pyr_from,
        p1,
        p0.copy(),
        winSize=win,
        maxLevel=min(max_level, cfg.klt_backward_levels),
        criteria=criteria,
        flags=cv2.OPTFLOW_USE_INITIAL_FLOW,
    )
    fb = np.linalg.norm(p0_back.reshape(-1, 2) - p0.reshape(-1, 2), axis=1)
    ok &= (st2.ravel() == 1) & (fb < cfg.klt_fb_max_error_px)
    return pts.astype(np.float32), ok


def essential_ransac(
    x0: np.ndarray, x1: np.ndarray, threshold: float, prob: float = 0.999
) -> tuple[np.ndarray, np.ndarray] | None:
    """Essential matrix (3, 3) and inlier mask from normalised matches ``x0 -> x1`` (N, 2) by
    OpenCV's five-point RANSAC, or None where there is none.

    Why not ``cv2.findEssentialMat`` alone: on degenerate matches (identical points: no motion)
    OpenCV 5.1 raises in its polynomial solver where 4.x returned no solution; either way it
    is "no essential matrix" to the caller.
    """
    try:
        e, mask = cv2.findEssentialMat(
            x0, x1, np.eye(3), method=cv2.RANSAC, prob=prob, threshold=threshold
        )
    except cv2.error:
        return None
    if e is None or e.shape != (3, 3) or mask is None:
        return None
    return e, mask

"""Affine KLT refinement of tracked points against the patch where each track was born.

Why: frame-to-frame KLT (OpenCV, translation only) drifts. Its window deforms as the view
changes (scale, rotation, foreshortening) and the best *translation* of a deformed window is
not the same surface point. Measured on the synthetic room (figure8, ground-truth depth and
poses, ``python -m tools.bench_klt_drift``): with a 21-px window the median error is 0.26 px
after 1 s and 0.63 px after 4 s (0.13 / 0.29 with an 11-px window), and it was no better when
each frame was tracked straight from the first one, so it is a bias of the model, not an
accumulation of noise. Re-fitting the track to its *first* patch with an affine warp removes
that bias: the warp absorbs the deformation and its translation is the first patch's centre.
Measured the same way: 0.053 px after 1 s, 0.063 px after 4 s (90th percentile 0.28 px).

The solver is inverse-compositional Lucas-Kanade (Baker & Matthews 2004) with six affine
parameters, zero-mean patches and a per-patch gain (robust to a brightness offset and to
exposure / gain changes, :func:`_residuals`), vectorised over all points:
the template's steepest-descent images and Hessians are computed once per track, each
iteration samples every patch with one ``cv2.remap`` call. Bicubic sampling: with bilinear
the fit locks towards whole pixels (0.05 px off on a known sub-pixel shift, 0.01 bicubic). OpenCV has no affine KLT and the
per-patch ``findTransformECC`` costs ~100x more.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np


@dataclass(frozen=True, eq=False)
class AffineTemplates:
    """Zero-mean template patches and their inverse-compositional Jacobians.

    ``patches`` (N, P): template intensities at offsets ``offsets`` (P, 2) from the track's
    birth pixel; ``steepest_t`` (N, 6, P): the steepest-descent images, transposed for batched
    matrix products; ``hessian_inv`` (N, 6, 6); ``valid`` (N,) False where the patch is too weak
    (flat or edge-like texture) to fit six parameters.
    """

    patches: np.ndarray
    steepest_t: np.ndarray
    hessian_inv: np.ndarray
    valid: np.ndarray
    offsets: np.ndarray

    def __len__(self) -> int:
        return len(self.patches)

    def take(self, index: np.ndarray) -> AffineTemplates:
        return AffineTemplates(
            self.patches[index],
            self.steepest_t[index],
            self.hessian_inv[index],
            self.valid[index],
            self.offsets,
        )

    @staticmethod
    def concatenate(parts: list[AffineTemplates], half_window_px: int) -> AffineTemplates:
        if not parts:
            return empty_templates(half_window_px)
        return AffineTemplates(
            np.concatenate([p.patches for p in parts]),
            np.concatenate([p.steepest_t for p in parts]),
            np.concatenate([p.hessian_inv for p in parts]),
            np.concatenate([p.valid for p in parts]),
            parts[0].offsets,
        )


def _offsets(half_window_px: int) -> np.ndarray:
    r = np.arange(-half_window_px, half_window_px + 1, dtype=np.float32)
    yy, xx = np.meshgrid(r, r, indexing="ij")
    return np.stack([xx.ravel(), yy.ravel()], axis=1)


def empty_templates(half_window_px: int) -> AffineTemplates:
    offsets = _offsets(half_window_px)
    p = len(offsets)
    return AffineTemplates(
        np.zeros((0, p), np.float32),
        np.zeros((0, 6, p), np.float32),
        np.zeros((0, 6, 6), np.float32),
        np.zeros(0, bool),
        offsets,
    )


def sample_image(image: np.ndarray, xs: np.ndarray, ys: np.ndarray) -> np.ndarray:
    """Bilinear samples of ``image`` at pixel coordinates ``xs``, ``ys`` (N, P): (N, P) float32."""
    if xs.size == 0:
        return np.zeros(xs.shape, np.float32)
    out = cv2.remap(
        image,
        np.ascontiguousarray(xs, dtype=np.float32),
        np.ascontiguousarray(ys, dtype=np.float32),
        interpolation=cv2.INTER_CUBIC,
        borderMode=cv2.BORDER_REPLICATE,
    )
    return out.astype(np.float32)


def build_templates(
    image: np.ndarray, pts_px: np.ndarray, half_window_px: int, min_eigen: float = 1e-4
) -> AffineTemplates:
    """Templates of the points ``pts_px`` (N, 2) in ``image`` (grey uint8).

    A template is ``valid`` when the smaller eigenvalue of its mean gradient matrix exceeds
    ``min_eigen`` * 255^2 (1e-4: a gradient of ~2.5 grey levels per pixel) and its 6x6 system
    is well conditioned. With 1e-3, 18% of the front end's corners were left to drift and the
    90th percentile error after 4 s was 1.0 px instead of 0.33 (``tools.bench_klt_drift``).
    """
    offsets = _offsets(half_window_px)
    pts = np.asarray(pts_px, dtype=np.float32).reshape(-1, 2)
    n, p = len(pts), len(offsets)
    if n == 0:
        return empty_templates(half_window_px)
    # intensities and central-difference gradients at sub-pixel positions (the birth pixel is
    # sub-pixel, so the template is resampled, not cut from the pixel grid)
    xs = pts[:, 0:1] + offsets[None, :, 0]
    ys = pts[:, 1:2] + offsets[None, :, 1]
    vals = sample_image(
        image,
        np.concatenate([xs, xs + 0.5, xs - 0.5, xs, xs]),
        np.concatenate([ys, ys, ys, ys + 0.5, ys - 0.5]),
    ).reshape(5, n, p)
    t = vals[0] - vals[0].mean(axis=1, keepdims=True)
    gx = vals[1] - vals[2]
    gy = vals[3] - vals[4]
    ox, oy = offsets[None, :, 0], offsets[None, :, 1]
    # warp x' = (1 + a0) x + a2 y + a4, y' = a1 x + (1 + a3) y + a5
    sd_t = np.stack([gx * ox, gy * ox, gx * oy, gy * oy, gx, gy], axis=1)
    sd_t -= sd_t.mean(axis=2, keepdims=True)  # zero-mean patches: the mean is projected out
    h = sd_t @ sd_t.transpose(0, 2, 1)
    # weak patches: the smaller eigenvalue of the translation block (mean squared gradient)
    trans = h[:, 4:, 4:] / p
    tr = trans[:, 0, 0] + trans[:, 1, 1]
    det = trans[:, 0, 0] * trans[:, 1, 1] - trans[:, 0, 1] ** 2
    lam_min = 0.5 * (tr - np.sqrt(np.maximum(tr * tr - 4 * det, 0.0)))
    valid = lam_min > min_eigen * 255.0**2
    eig = np.linalg.eigvalsh(h.astype(np.float64))
    valid &= eig[:, 0] > 1e-7 * eig[:, -1]
    hinv = np.zeros_like(h)
    if valid.any():
        hinv[valid] = np.linalg.inv(h[valid].astype(np.float64)).astype(np.float32)
    return AffineTemplates(t.astype(np.float32), sd_t.astype(np.float32), hinv, valid, offsets)


@dataclass(frozen=True, eq=False)
class AffineFit:
    """``pts_px`` (N, 2): where each template's centre lies in the image; ``linear`` (N, 2, 2):
    the fitted deformation (pass it back as the next guess); ``ok`` (N,): converged, inside,
    not degenerate; ``rms`` (N,): intensity residual after gain and bias matching (grey
    levels); ``ncc`` (N,): normalised cross-correlation of the fitted patch and the template."""

    pts_px: np.ndarray
    linear: np.ndarray
    ok: np.ndarray
    rms: np.ndarray
    ncc: np.ndarray


def _inv2(m: np.ndarray) -> np.ndarray:
    """Inverses of (N, 2, 2) matrices."""
    det = m[:, 0, 0] * m[:, 1, 1] - m[:, 0, 1] * m[:, 1, 0]
    out = np.empty_like(m)
    out[:, 0, 0] = m[:, 1, 1]
    out[:, 1, 1] = m[:, 0, 0]
    out[:, 0, 1] = -m[:, 0, 1]
    out[:, 1, 0] = -m[:, 1, 0]
    return out / det[:, None, None]


def _residuals(
    templates: AffineTemplates, image: np.ndarray, lin: np.ndarray, pts: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Gain- and bias-matched residual (N, P) of each template warped into ``image``, the
    warped coordinates (N, 2, P) and the normalised cross-correlation (N,) of the two patches.

    The warped patch is made zero-mean (bias) and scaled by the least-squares gain that best
    matches it to the template (``<t, v> / <v, v>``, kept within [1/4, 4]): an exposure or gain
    change between the track's birth and now (auto-exposure steps of 3 dB, vignetting as the
    point crosses the image) leaves the fit unbiased. Without the gain a 41 % brighter image
    moved the fit by 0.14 px (median) on a textured patch, instead of 0.01."""
    coords = lin @ templates.offsets.T[None] + pts[:, :, None]
    vals = sample_image(image, coords[:, 0], coords[:, 1])
    v0 = vals - vals.mean(axis=1, keepdims=True)
    vv = np.einsum("np,np->n", v0, v0)
    tv = np.einsum("np,np->n", templates.patches, v0)
    tt = np.einsum("np,np->n", templates.patches, templates.patches)
    gain = np.clip(tv / np.maximum(vv, 1e-6), 0.25, 4.0).astype(np.float32)
    ncc = tv / np.sqrt(np.maximum(vv * tt, 1e-12))
    err = v0 * gain[:, None] - templates.patches
    return err, coords, ncc.astype(np.float32)


def refine_affine(
    templates: AffineTemplates,
    image: np.ndarray,
    guess_px: np.ndarray,
    guess_linear: np.ndarray | None = None,
    iterations: int = 6,
    max_shift_px: float = 2.0,
    max_rms: float = 25.0,
    min_ncc: float = 0.85,
) -> AffineFit:
    """Fit each template into ``image`` starting at ``guess_px`` (N, 2) with the deformation
    ``guess_linear`` (N, 2, 2; identity if None). ``ok`` is False for weak templates, fits that
    moved more than ``max_shift_px`` from the guess, left the image, degenerated (scale outside
    1/3-3), ended with an RMS residual (after gain and bias matching) above ``max_rms`` grey
    levels, or whose patch correlates with the template by less than ``min_ncc`` (normalised
    cross-correlation: the gain matching lets any patch's residual shrink towards the
    template's own spread, so the residual alone no longer tells a wrong place)."""
    n = len(templates)
    guess = np.asarray(guess_px, dtype=np.float32).reshape(n, 2)
    lin = np.empty((n, 2, 2), np.float32)
    lin[:] = np.eye(2) if guess_linear is None else guess_linear
    pts = guess.copy()
    for _ in range(iterations):
        # every row every iteration: selecting the unconverged rows copied more than it saved
        err, _, _ = _residuals(templates, image, lin, pts)
        dp = (templates.hessian_inv @ (templates.steepest_t @ err[:, :, None]))[:, :, 0]
        # inverse compositional update: W <- W o W(dp)^-1
        d_lin = np.empty((n, 2, 2), np.float32)
        d_lin[:, 0, 0] = 1.0 + dp[:, 0]
        d_lin[:, 1, 0] = dp[:, 1]
        d_lin[:, 0, 1] = dp[:, 2]
        d_lin[:, 1, 1] = 1.0 + dp[:, 3]
        d_inv = _inv2(d_lin)
        pts -= (lin @ (d_inv @ dp[:, 4:, None]))[:, :, 0]
        lin = lin @ d_inv
    err, coords, ncc = _residuals(templates, image, lin, pts)
    rms = np.sqrt(np.mean(err * err, axis=1))
    h_img, w_img = image.shape[:2]
    det = lin[:, 0, 0] * lin[:, 1, 1] - lin[:, 0, 1] * lin[:, 1, 0]
    sv = np.linalg.svd(lin, compute_uv=False) if n else np.ones((0, 2), np.float32)
    inside = (
        (coords[:, 0].min(axis=1, initial=np.inf) >= 0)
        & (coords[:, 1].min(axis=1, initial=np.inf) >= 0)
        & (coords[:, 0].max(axis=1, initial=-np.inf) <= w_img - 1)
        & (coords[:, 1].max(axis=1, initial=-np.inf) <= h_img - 1)
    )
    ok = (
        templates.valid
        & np.isfinite(pts).all(axis=1)
        & (np.linalg.norm(pts - guess, axis=1) <= max_shift_px)
        & inside
        & (det > 0)
        & (sv[:, -1] > 1 / 3)
        & (sv[:, 0] < 3.0)
        & (rms <= max_rms)
        & (ncc >= min_ncc)
    )
    return AffineFit(pts, lin, ok, rms.astype(np.float32), ncc)


class TrackTemplates:
    """The birth patch of every live landmark track, and its last fitted deformation.

    Rows are kept in landmark-id order (ids only grow), so lookups are one ``searchsorted``.
    The front end re-fits a share of its tracks every frame (:meth:`refine`), and at keyframes
    forgets the tracks it dropped (:meth:`keep_only`) and adds the landmarks it creates
    (:meth:`add`).
    """

    def __init__(self, half_window_px: int, iterations: int, min_ncc: float = 0.85) -> None:
        self.half_window_px = half_window_px
        self.iterations = iterations
        self.min_ncc = min_ncc
        self.clear()

    def clear(self) -> None:
        self._pending: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []
        self.ids = np.zeros(0, np.int64)
        self.templates = empty_templates(self.half_window_px)
        self.linear = np.zeros((0, 2, 2), np.float32)

    def __len__(self) -> int:
        return len(self.ids)

    def _rows(self, landmark_ids: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(found mask over ``landmark_ids``, their rows)."""
        ids = np.asarray(landmark_ids, dtype=np.int64)
        pos = np.searchsorted(self.ids, ids)
        pos_c = np.minimum(pos, max(len(self.ids) - 1, 0))
        found = (pos < len(self.ids)) & (self.ids[pos_c] == ids) if len(self.ids) else pos < 0
        return found, pos_c[found]

    def refine(
        self, landmark_ids: np.ndarray, px: np.ndarray, image: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Tracked pixels ``px`` (N, 2) of ``landmark_ids`` (N,; -1 for none), re-fitted where
        a template exists and its fit is good, the others unchanged. Returns ``(pixels,
        has_template, refitted)``, the last two (N,) bool."""
        self.build_pending()
        out = np.array(px, dtype=np.float32, copy=True)
        found, rows = self._rows(landmark_ids)
        refitted = np.zeros(len(out), bool)
        if len(rows) == 0:
            return out, found, refitted
        fit = refine_affine(
            self.templates.take(rows),
            image,
            out[found],
            self.linear[rows],
            iterations=self.iterations,
            min_ncc=self.min_ncc,
        )
        idx = np.flatnonzero(found)
        out[idx[fit.ok]] = fit.pts_px[fit.ok]
        refitted[idx[fit.ok]] = True
        self.linear[rows[fit.ok]] = fit.linear[fit.ok]
        return out, found, refitted

    def keep_only(self, landmark_ids: np.ndarray) -> None:
        self.build_pending()
        keep = np.isin(self.ids, np.asarray(landmark_ids, dtype=np.int64))
        if keep.all():
            return
        rows = np.flatnonzero(keep)
        self.ids = self.ids[rows]
        self.templates = self.templates.take(rows)
        self.linear = self.linear[rows]

    def add(self, landmark_ids: np.ndarray, px: np.ndarray, image: np.ndarray) -> None:
        """New landmarks (ids larger than every stored one) born at ``px`` in ``image``. Their
        templates are cut at the next :meth:`refine` (``build_pending``), which keeps the cost
        off the keyframe's frame, the front end's slowest."""
        ids = np.asarray(landmark_ids, dtype=np.int64)
        if len(ids):
            self._pending.append((ids.copy(), np.asarray(px, np.float32).copy(), image))

    def restore(
        self, landmark_ids: np.ndarray, templates: AffineTemplates, linear: np.ndarray
    ) -> None:
        """Tracks of older landmarks found again (:mod:`slam.frontend.landmark_map`), with
        templates made from their birth patches and their fitted warps ``linear`` (N, 2, 2):
        inserted in id order."""
        self.build_pending()
        ids = np.asarray(landmark_ids, dtype=np.int64)
        if len(ids) == 0:
            return
        keep = ~np.isin(self.ids, ids)
        all_ids = np.concatenate([self.ids[keep], ids])
        order = np.argsort(all_ids, kind="stable")
        merged = AffineTemplates.concatenate(
            [self.templates.take(np.flatnonzero(keep)), templates], self.half_window_px
        )
        self.ids = all_ids[order]
        self.templates = merged.take(order)
        self.linear = np.concatenate([self.linear[keep], np.asarray(linear, np.float32)])[order]

    def build_pending(self) -> None:
        pending, self._pending = self._pending, []
        for ids, px, image in pending:
            self._build(ids, px, image)

    def _build(self, ids: np.ndarray, px: np.ndarray, image: np.ndarray) -> None:
        if len(self.ids) and ids.min() <= self.ids[-1]:
            raise ValueError("landmark templates must be added in increasing id order")
        order = np.argsort(ids)
        new = build_templates(image, np.asarray(px)[order], self.half_window_px)
        self.templates = AffineTemplates.concatenate([self.templates, new], self.half_window_px)
        self.ids = np.concatenate([self.ids, ids[order]])
        eye = np.broadcast_to(np.eye(2, dtype=np.float32), (len(ids), 2, 2))
        self.linear = np.concatenate([self.linear, eye])

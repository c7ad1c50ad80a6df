"""PatchMatch multi-view stereo (Bleyer et al. 2011; the red-black scheme of Gipuma, 2015).

Each reference pixel holds a plane hypothesis: a unit normal ``n`` (camera frame, facing the
camera) and its depth ``Z`` at the pixel; the plane is ``n . X = c`` with ``c = Z n . r_p`` for the
pixel's ray ``r_p = K^-1 (u, v, 1)``. Fronto-parallel mode keeps ``n = (0, 0, -1)``.

- **Cost**: ZNCC over a sparse window (``window`` x ``window`` samples, ``dilation`` pixels
  apart). Every window sample ``q`` is lifted onto the pixel's plane (``X_q = c / (n . r_q) r_q``),
  projected into each source view and sampled bilinearly (``cv2.remap`` on the flat list of
  pixels being updated, so only those pixels are evaluated). Views are aggregated as in the
  plane sweep: mean of the best ``k``.
- **Random initialisation**: inverse depth uniform in the range, normals random within 60 deg
  of the viewing direction (slanted mode).
- **Propagation**: red-black checkerboard; all red pixels are updated at once from the current
  hypotheses of their black neighbours (4-neighbours and the 4 pixels 3 steps away, which
  spreads good planes faster), then black from red, in numpy.
- **Refinement**: each pixel also tries a perturbation of its own hypothesis whose size halves
  every iteration (inverse depth and normal), plus one fresh random hypothesis.
- Output filtering: best ZNCC >= ``min_score`` and textured window.

Same input convention as :func:`mapping.planesweep.plane_sweep` (undistorted images, pinhole K,
``src_from_ref``); returns the same :class:`~mapping.planesweep.DepthResult`.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import cv2
import numpy as np

from mapping.planesweep import DepthResult, SourceView, to_gray_f32


@dataclass(frozen=True)
class PatchMatchConfig:
    """Parameters of :func:`patchmatch_stereo`."""

    depth_min_m: float = 0.4
    depth_max_m: float = 10.0
    iterations: int = 3
    """Red-black sweeps (each updates every pixel once)."""
    window: int = 5
    """Window samples per side (odd)."""
    dilation: int = 2
    """Pixels between window samples (a 5x5 window with dilation 2 spans 9x9 pixels)."""
    slanted: bool = True
    """Estimate plane normals (False: fronto-parallel planes only)."""
    best_k: int | None = None
    """Views averaged per pixel (the best ones); None = ceil(views / 2)."""
    min_score: float = 0.5
    """Drop pixels whose final ZNCC is below this."""
    min_texture: float = 3.0
    """Drop pixels whose window standard deviation (grey levels) is below this."""
    seed: int = 0
    """Random generator seed (results are deterministic for a seed)."""


class _Problem:
    """Images, cameras and the window statistics of the reference."""

    def __init__(
        self, ref: np.ndarray, K: np.ndarray, sources: Sequence[SourceView], cfg: PatchMatchConfig
    ):
        self.cfg = cfg
        self.ref = ref
        self.h, self.w = ref.shape
        self.K = K
        self.srcs = [to_gray_f32(s.image) for s in sources]
        self.P = [(s.K @ s.src_from_ref[:3, :3]).astype(np.float32) for s in sources]  # K_s R
        self.p = [(s.K @ s.src_from_ref[:3, 3]).astype(np.float32) for s in sources]  # K_s t
        half = cfg.window // 2
        g = np.arange(-half, half + 1) * cfg.dilation
        self.offsets = [(int(dx), int(dy)) for dy in g for dx in g]
        self.pad = half * cfg.dilation
        self.ref_pad = cv2.copyMakeBorder(ref, *(4 * [self.pad]), cv2.BORDER_REFLECT)
        # Window mean and std of the reference at every pixel over the sparse pattern.
        s1 = np.zeros_like(ref)
        s2 = np.zeros_like(ref)
        for dx, dy in self.offsets:
            r = self.ref_pad[
                self.pad + dy : self.pad + dy + self.h, self.pad + dx : self.pad + dx + self.w
            ]
            s1 += r
            s2 += r * r
        n = len(self.offsets)
        self.ref_mean = s1 / n
        self.ref_std = np.sqrt(np.maximum(s2 / n - self.ref_mean**2, 0.0))
        self.k = cfg.best_k or (len(sources) + 1) // 2
        self.inv_fx = np.float32(1.0 / K[0, 0])
        self.inv_fy = np.float32(1.0 / K[1, 1])

    def ray(self, u: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return (u - self.K[0, 2]) * self.inv_fx, (v - self.K[1, 2]) * self.inv_fy

    def cost(
        self, u: np.ndarray, v: np.ndarray, normal: np.ndarray, depth: np.ndarray
    ) -> np.ndarray:
        """Aggregated ZNCC (higher is better) of plane hypotheses at pixels (u, v) (int arrays)."""
        m = len(u)
        rx, ry = self.ray(u.astype(np.float32), v.astype(np.float32))
        nx, ny, nz = normal[:, 0], normal[:, 1], normal[:, 2]
        c = depth * (nx * rx + ny * ry + nz)  # plane constant n . X_p
        sums = [
            [np.zeros(m, np.float32) for _ in range(3)] for _ in self.srcs
        ]  # s, s^2, r*s per view
        valid = [np.ones(m, bool) for _ in self.srcs]
        for dx, dy in self.offsets:
            uq = u + dx
            vq = v + dy
            r = self.ref_pad[vq + self.pad, uq + self.pad]
            qx, qy = self.ray(uq.astype(np.float32), vq.astype(np.float32))
            denom = nx * qx + ny * qy + nz
            lam = c / np.where(np.abs(denom) > 1e-6, denom, np.float32(1e-6))
            for j, src in enumerate(self.srcs):
                kr, kt = self.P[j], self.p[j]
                hx = lam * (kr[0, 0] * qx + kr[0, 1] * qy + kr[0, 2]) + kt[0]
                hy = lam * (kr[1, 0] * qx + kr[1, 1] * qy + kr[1, 2]) + kt[1]
                hz = lam * (kr[2, 0] * qx + kr[2, 1] * qy + kr[2, 2]) + kt[2]
                ok = hz > 1e-3
                inv = np.float32(1.0) / np.where(ok, hz, np.float32(1.0))
                s = _sample(src, hx * inv, hy * inv)
                valid[j] &= ok & ~np.isnan(s)
                s = np.nan_to_num(s)
                acc = sums[j]
                acc[0] += s
                acc[1] += s * s
                acc[2] += r * s
        n = np.float32(len(self.offsets))
        mr = self.ref_mean[v, u]
        sr = self.ref_std[v, u]
        scores = []
        for j in range(len(self.srcs)):
            s1, s2, rs = sums[j]
            ms = s1 / n
            var_s = np.maximum(s2 / n - ms * ms, np.float32(1e-2))
            z = (rs / n - mr * ms) / (np.maximum(sr, np.float32(1e-3)) * np.sqrt(var_s))
            scores.append(np.where(valid[j], z, np.float32(-1.0)))
        if len(scores) == 1:
            return scores[0]
        stack = np.sort(np.stack(scores), axis=0)[::-1]
        return stack[: self.k].mean(axis=0)


_REMAP_COLS = 1024  # cv2.remap wants both map dimensions below 32767


def _sample(img: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Bilinear samples of img at float pixel positions (flat arrays); NaN outside."""
    m = len(x)
    rows = -(-m // _REMAP_COLS)
    mx = np.full(rows * _REMAP_COLS, -10.0, np.float32)
    my = np.full(rows * _REMAP_COLS, -10.0, np.float32)
    mx[:m] = x
    my[:m] = y
    out = cv2.remap(
        img,
        mx.reshape(rows, _REMAP_COLS),
        my.reshape(rows, _REMAP_COLS),
        cv2.INTER_LINEAR,
        borderMode=cv2.BORDER_CONSTANT,
        borderValue=np.nan,
    )
    return out.reshape(-1)[:m]


def _random_normals(rng: np.random.Generator, n: int, rx: np.ndarray, ry: np.ndarray) -> np.ndarray:
    """Unit normals facing the camera, within 60 deg of the reversed viewing ray."""
    view = -np.stack([rx, ry, np.ones_like(rx)], 1)
    view /= np.linalg.norm(view, axis=1, keepdims=True)
    rnd = rng.normal(size=(n, 3)).astype(np.float32)
    rnd /= np.linalg.norm(rnd, axis=1, keepdims=True)
    out = view + 0.9 * rnd  # |rnd| = 1 < 1 / sin(60 deg): stays on the camera side
    return (out / np.linalg.norm(out, axis=1, keepdims=True)).astype(np.float32)


def _perturb_normals(rng: np.random.Generator, normal: np.ndarray, scale: float) -> np.ndarray:
    out = normal + rng.normal(scale=scale, size=normal.shape).astype(np.float32)
    out /= np.linalg.norm(out, axis=1, keepdims=True)
    out[out[:, 2] > -0.2] = normal[out[:, 2] > -0.2]  # keep facing the camera
    return out.astype(np.float32)


def patchmatch_stereo(
    ref_image: np.ndarray,
    K_ref: np.ndarray,
    sources: Sequence[SourceView],
    config: PatchMatchConfig | None = None,
) -> DepthResult:
    """Depth map of the reference view by PatchMatch (see the module docstring)."""
    cfg = config or PatchMatchConfig()
    if not sources:
        raise ValueError("patchmatch_stereo needs at least one source view")
    rng = np.random.default_rng(cfg.seed)
    prob = _Problem(to_gray_f32(ref_image), np.asarray(K_ref, float), sources, cfg)
    h, w = prob.h, prob.w
    inv_lo, inv_hi = 1.0 / cfg.depth_max_m, 1.0 / cfg.depth_min_m
    vv, uu = np.mgrid[0:h, 0:w]
    uu = uu.ravel().astype(np.int32)
    vv = vv.ravel().astype(np.int32)
    rx, ry = prob.ray(uu.astype(np.float32), vv.astype(np.float32))
    n_px = h * w
    depth = (1.0 / rng.uniform(inv_lo, inv_hi, n_px)).astype(np.float32)
    fronto = np.tile(np.array([0.0, 0.0, -1.0], np.float32), (n_px, 1))
    normal = _random_normals(rng, n_px, rx, ry) if cfg.slanted else fronto.copy()
    cost = prob.cost(uu, vv, normal, depth)

    red = ((uu + vv) % 2 == 0).nonzero()[0]
    black = ((uu + vv) % 2 == 1).nonzero()[0]
    neighbours = [(-1, 0), (1, 0), (0, -1), (0, 1), (-3, 0), (3, 0), (0, -3), (0, 3)]
    for it in range(cfg.iterations):
        step_inv = (inv_hi - inv_lo) * 0.25 * 0.5**it
        step_n = 0.5 * 0.5**it
        for idx in (red, black):
            u, v = uu[idx], vv[idx]
            prx, pry = rx[idx], ry[idx]
            cands_n: list[np.ndarray] = []
            cands_d: list[np.ndarray] = []
            for dx, dy in neighbours:  # odd offsets: always the other colour
                un = np.clip(u + dx, 0, w - 1)
                vn = np.clip(v + dy, 0, h - 1)
                j = vn * w + un
                nrm = normal[j]
                # Depth at this pixel of the neighbour's plane: c_j / (n_j . r_p).
                c_j = depth[j] * (nrm[:, 0] * rx[j] + nrm[:, 1] * ry[j] + nrm[:, 2])
                den = nrm[:, 0] * prx + nrm[:, 1] * pry + nrm[:, 2]
                d = np.where(np.abs(den) > 1e-6, c_j / np.where(den == 0, 1e-6, den), -1.0)
                cands_n.append(nrm)
                cands_d.append(d.astype(np.float32))
            inv = 1.0 / depth[idx] + rng.uniform(-step_inv, step_inv, len(idx))
            cands_d.append((1.0 / np.clip(inv, inv_lo, inv_hi)).astype(np.float32))
            cands_n.append(
                _perturb_normals(rng, normal[idx], step_n) if cfg.slanted else fronto[idx]
            )
            cands_d.append((1.0 / rng.uniform(inv_lo, inv_hi, len(idx))).astype(np.float32))
            cands_n.append(_random_normals(rng, len(idx), prx, pry) if cfg.slanted else fronto[idx])
            best_c = cost[idx]
            best_d = depth[idx]
            best_n = normal[idx]
            for nrm, d in zip(cands_n, cands_d):
                in_range = (d >= cfg.depth_min_m) & (d <= cfg.depth_max_m)
                if not in_range.any():
                    continue
                c = prob.cost(u, v, nrm, np.where(in_range, d, best_d))
                better = in_range & (c > best_c)
                best_c = np.where(better, c, best_c)
                best_d = np.where(better, d, best_d)
                best_n = np.where(better[:, None], nrm, best_n)
            cost[idx] = best_c
            depth[idx] = best_d
            normal[idx] = best_n

    score = cost.reshape(h, w)
    raw = depth.reshape(h, w)
    textured = prob.ref_std >= cfg.min_texture
    keep = textured & (score >= cfg.min_score)
    out = np.where(keep, raw, 0.0).astype(np.float32)
    return DepthResult(out, raw, score, np.ones((h, w), np.float32), textured)

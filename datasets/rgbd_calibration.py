"""Colour-camera calibration of an unregistered RGB-D folder, from the data itself.

Datasets such as Microsoft 7-Scenes give depth-camera poses (KinectFusion) and the depth
intrinsics, but neither the colour camera's intrinsics nor where it sits relative to the depth
camera, nor when its frames were taken. This module estimates, from the frames themselves:

- the colour intrinsics ``fx, fy, cx, cy`` and radial distortion ``k1, k2`` (radtan, p = 0);
- the rigid ``color_from_depth`` (4x4);
- a colour-versus-depth time offset ``tau`` in frames: colour frame ``i`` was exposed at depth
  time ``i + tau``; its pose is interpolated between the neighbouring depth poses.

Measurement: colour frames ``ref`` and ``src`` (a few frames apart) are matched with KLT
(forward-backward checked). A reference feature is lifted to 3-D with the reference's sensor
depth: the depth map is rendered into the colour image with the current estimate to find the
surface behind the feature, and a plane is fitted to that surface patch in the depth camera.
The residual is the reprojection error in the source colour image of the point where the
feature's colour ray meets that plane, with the relative motion from the dataset's poses:

    src_pixel = project(color_from_depth  depth_src(src + tau)^-1  depth_ref(ref)  X(theta))

The plane makes the lifted point a smooth function of the parameters (no re-association inside
the solver); the association is redone a few times (outer iterations). Both directions of each
pair are used. ``scipy.optimize.least_squares`` with a soft-L1 loss solves it.

Observability (honest limits): the focal length and principal point are well constrained by the
rotational motion; the extrinsic translation only through parallax against the measured depth
(its component along the viewing direction trades against the focal length); a small extrinsic
rotation about x/y and a principal-point shift are nearly interchangeable. The view-to-view
geometry (what a plane sweep needs) is determined best; the lateral depth-to-colour
registration least (on synthetic data 0.5 px median from 6.8 px at the start), because on a
smooth surface it only slides the lifted point along the surface. On real data the poses'
own per-frame error must be well below a pixel, or it is absorbed by these weak directions:
on 7-Scenes (KinectFusion poses, 1-3 px disagreement per 10-frame pair) only the focal length
was reproducible across calibration subsets (524-529 px).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Protocol

import cv2
import numpy as np
from scipy.optimize import least_squares
from tqdm import tqdm

from slam.core.calibration import CameraIntrinsics
from slam.core.geometry import invert_transform, so3_exp, so3_log


class RgbdSource(Protocol):
    """What the calibration reads (``datasets.rgbd_folder.RgbdFolder`` satisfies it)."""

    K: np.ndarray
    """Depth-camera intrinsics (3x3)."""

    def __len__(self) -> int: ...

    def color_rgb(self, i: int) -> np.ndarray: ...

    def depth_m(self, i: int) -> np.ndarray: ...

    def pose(self, i: int) -> np.ndarray:
        """world_from_depth (4x4) of frame i (position in the folder, 0-based)."""
        ...


@dataclass(frozen=True)
class ColorCalibrationConfig:
    """Parameters of :func:`calibrate_color_camera`."""

    initial_focal_px: float = 525.0
    """Starting focal length (Kinect v1 colour: about 525 px at 640x480)."""
    separate_focals: bool = True
    """Estimate fx and fy separately (else one f)."""
    distortion: bool = True
    """Estimate radial distortion k1, k2."""
    time_offset: bool = True
    """Estimate the colour-versus-depth time offset (frames)."""
    fixed: tuple[str, ...] = ()
    """Further parameters held at their start values, by name: fx, fy, cx, cy, k1, k2, rx, ry,
    rz (rotation vector of color_from_depth, rad), tx, ty, tz (its translation, m), tau."""
    max_corners: int = 500
    """KLT corners per reference image."""
    outer_iterations: int = 4
    """Re-associations of features with the depth surface."""
    loss_scale_px: float = 1.0
    """Soft-L1 loss scale (pixels)."""
    patch_px: int = 7
    """Side of the depth patch a plane is fitted to (depth pixels, odd)."""
    max_plane_rms: float = 0.006
    """Drop patches whose plane-fit RMS exceeds this fraction of their depth."""
    max_reassoc_px: float = 3.0
    """Residuals above this (px) after an outer iteration do not count in the reported RMS."""
    min_depth_m: float = 0.3
    """Ignore depth below this (m)."""


@dataclass(frozen=True, eq=False)
class ColorCalibration:
    """A colour camera relative to the depth camera of an RGB-D folder."""

    intrinsics: CameraIntrinsics
    """Colour intrinsics (radtan with p1 = p2 = 0)."""
    color_from_depth: np.ndarray
    """Rigid 4x4 transform from the depth camera to the colour camera."""
    time_offset_frames: float = 0.0
    """Colour frame i was exposed at depth time i + this (frames)."""
    rms_px_initial: float = float("nan")
    """RMS reprojection error (px) of the inliers at the starting estimate."""
    rms_px: float = float("nan")
    """RMS reprojection error (px) of the inliers at the estimate."""
    median_px_initial: float = float("nan")
    median_px: float = float("nan")
    num_points: int = 0
    """Lifted feature points used in the final solve."""
    std: dict[str, float] = field(default_factory=dict)
    """Approximate 1-sigma of each free parameter (from the Gauss-Newton covariance)."""

    def world_from_color(self, poses: PoseInterpolator, i: int) -> np.ndarray:
        """world_from_color (4x4) of colour frame i."""
        return poses.at(i + self.time_offset_frames) @ invert_transform(self.color_from_depth)

    def color_from_depth_frame(
        self, poses: PoseInterpolator, color_i: int, depth_i: int
    ) -> np.ndarray:
        """Transform from depth frame ``depth_i`` (at its own time) to colour frame ``color_i``."""
        return invert_transform(self.world_from_color(poses, color_i)) @ poses.at(depth_i)


class PoseInterpolator:
    """world_from_depth at fractional frame positions (SE(3) interpolation between neighbours;
    constant beyond the ends). Poses are read on demand and cached."""

    def __init__(self, source: RgbdSource) -> None:
        self._source = source
        self._n = len(source)
        self._cache: dict[int, np.ndarray] = {}
        self._log_step: dict[int, np.ndarray] = {}  # rotation vector from pose i to pose i + 1

    def pose(self, i: int) -> np.ndarray:
        i = int(min(max(i, 0), self._n - 1))
        if i not in self._cache:
            self._cache[i] = np.asarray(self._source.pose(i), dtype=float)
        return self._cache[i]

    def at(self, t: float) -> np.ndarray:
        t = min(max(float(t), 0.0), self._n - 1.0)
        i0 = int(np.floor(t))
        a = t - i0
        p0 = self.pose(i0)
        if a < 1e-12:
            return p0.copy()
        p1 = self.pose(i0 + 1)
        if i0 not in self._log_step:
            self._log_step[i0] = so3_log(p0[:3, :3].T @ p1[:3, :3])
        out = np.eye(4)
        out[:3, :3] = p0[:3, :3] @ so3_exp(a * self._log_step[i0])
        out[:3, 3] = (1 - a) * p0[:3, 3] + a * p1[:3, 3]
        return out


# Parameter vector: fx, fy, cx, cy, k1, k2, rotvec (3), t (3), tau.
_NAMES = ("fx", "fy", "cx", "cy", "k1", "k2", "rx", "ry", "rz", "tx", "ty", "tz", "tau")


def _free_mask(cfg: ColorCalibrationConfig) -> np.ndarray:
    free = np.ones(len(_NAMES), bool)
    free[1] = cfg.separate_focals
    free[4:6] = cfg.distortion
    free[12] = cfg.time_offset
    for name in cfg.fixed:
        if name not in _NAMES:
            raise ValueError(f"unknown parameter {name!r}; expected one of {_NAMES}")
        free[_NAMES.index(name)] = False
    return free


def _full(theta_free: np.ndarray, base: np.ndarray, free: np.ndarray, tie_fy: bool) -> np.ndarray:
    """All 13 parameters from the free ones (fy = fx when ``tie_fy``)."""
    p = base.copy()
    p[free] = theta_free
    if tie_fy:
        p[1] = p[0]
    return p


def _distort(p: np.ndarray, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    r2 = x * x + y * y
    s = 1 + p[4] * r2 + p[5] * r2 * r2
    return p[0] * x * s + p[2], p[1] * y * s + p[3]


def _undistort(p: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """Distorted pixels (N, 2) -> normalised coordinates (N, 2) (fixed-point iteration)."""
    xd = (uv[:, 0] - p[2]) / p[0]
    yd = (uv[:, 1] - p[3]) / p[1]
    x, y = xd.copy(), yd.copy()
    for _ in range(20):
        r2 = x * x + y * y
        s = 1 + p[4] * r2 + p[5] * r2 * r2
        x, y = xd / s, yd / s
    return np.stack([x, y], 1)


def _extrinsic(p: np.ndarray) -> np.ndarray:
    out = np.eye(4)
    out[:3, :3] = so3_exp(p[6:9])
    out[:3, 3] = p[9:12]
    return out


def _intrinsics(p: np.ndarray, width: int, height: int) -> CameraIntrinsics:
    return CameraIntrinsics(
        width,
        height,
        float(p[0]),
        float(p[1]),
        float(p[2]),
        float(p[3]),
        "radtan",
        (float(p[4]), float(p[5]), 0.0, 0.0),
    )


def match_klt(gray_a: np.ndarray, gray_b: np.ndarray, max_corners: int) -> tuple[np.ndarray, ...]:
    """KLT matches a -> b with a forward-backward check (0.5 px): pixels (N, 2) in a and in b."""
    pa = cv2.goodFeaturesToTrack(gray_a, max_corners, 0.01, 8, blockSize=7)
    if pa is None:
        return np.zeros((0, 2)), np.zeros((0, 2))
    params = dict(winSize=(21, 21), maxLevel=4)
    pb, st, _ = cv2.calcOpticalFlowPyrLK(gray_a, gray_b, pa, None, **params)
    pa2, st2, _ = cv2.calcOpticalFlowPyrLK(gray_b, gray_a, pb, None, **params)
    ok = (st.ravel() == 1) & (st2.ravel() == 1)
    ok &= np.linalg.norm((pa2 - pa).reshape(-1, 2), axis=1) < 0.5
    return pa.reshape(-1, 2)[ok].astype(float), pb.reshape(-1, 2)[ok].astype(float)


def depth_points(depth_m: np.ndarray, K: np.ndarray) -> np.ndarray:
    """Back-projected depth image (H, W, 3) in the depth camera (z = 0 where invalid)."""
    h, w = depth_m.shape
    v, u = np.mgrid[0:h, 0:w]
    z = depth_m.astype(float)
    return np.stack([(u - K[0, 2]) / K[0, 0] * z, (v - K[1, 2]) / K[1, 1] * z, z], -1)


def render_depth(
    depth_m: np.ndarray,
    K_depth: np.ndarray,
    dst_from_depth: np.ndarray,
    intrinsics: CameraIntrinsics,
    min_depth_m: float = 0.0,
) -> np.ndarray:
    """Sensor depth seen from another camera (z in that camera, metres; 0 = none), z-buffered.

    Every valid depth pixel is moved by ``dst_from_depth`` and projected with ``intrinsics``
    (distortion included; use a pinhole ``CameraIntrinsics`` for undistorted images) to the
    nearest pixel. Where several land on one pixel the nearest surface wins.
    """
    pts = depth_points(depth_m, K_depth).reshape(-1, 3)
    pts = pts[pts[:, 2] > min_depth_m]
    pc = pts @ dst_from_depth[:3, :3].T + dst_from_depth[:3, 3]
    pc = pc[pc[:, 2] > 1e-3]
    uv = np.round(intrinsics.project(pc)).astype(np.int64)
    w, h = intrinsics.width, intrinsics.height
    ok = (uv[:, 0] >= 0) & (uv[:, 0] < w) & (uv[:, 1] >= 0) & (uv[:, 1] < h)
    idx, z = uv[ok, 1] * w + uv[ok, 0], pc[ok, 2]
    order = np.lexsort((z, idx))  # by pixel, nearest first
    first = np.ones(len(order), bool)
    first[1:] = idx[order][1:] != idx[order][:-1]
    out = np.zeros(h * w)
    out[idx[order][first]] = z[order][first]
    return out.reshape(h, w).astype(np.float32)


def color_in_depth_camera(
    color_rgb: np.ndarray,
    depth_m: np.ndarray,
    K_depth: np.ndarray,
    intrinsics: CameraIntrinsics,
    color_from_depth: np.ndarray,
) -> np.ndarray:
    """The colour image resampled onto the depth image's pixels (registered to the depth).

    Each depth pixel's 3-D point is moved by ``color_from_depth`` (for a folder: the
    calibration's :meth:`ColorCalibration.color_from_depth_frame`) and projected with the colour
    ``intrinsics`` (distortion included); the colour there is sampled bilinearly. Pixels without
    depth or landing outside the colour image are 0. Occlusion is not checked: a depth point
    hidden from the colour camera takes the colour of what hides it.
    """
    h, w = depth_m.shape
    pts = depth_points(depth_m, K_depth).reshape(-1, 3)
    pc = pts @ color_from_depth[:3, :3].T + color_from_depth[:3, 3]
    ok = (pts[:, 2] > 0) & (pc[:, 2] > 1e-3)
    uv = np.full((h * w, 2), -1.0)
    uv[ok] = intrinsics.project(pc[ok])
    maps = uv.reshape(h, w, 2).astype(np.float32)
    out = cv2.remap(
        color_rgb, maps[..., 0], maps[..., 1], cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT
    )
    out[~ok.reshape(h, w)] = 0
    return out


@dataclass(frozen=True, eq=False)
class _PairData:
    ref: int
    src: int
    pix_ref: np.ndarray  # (N, 2) colour pixels in ref
    pix_src: np.ndarray  # (N, 2) matching colour pixels in src
    depth_ref: np.ndarray  # (H, W) sensor depth of ref (m)


@dataclass(frozen=True, eq=False)
class _Lifted:
    """Features with their depth-surface plane, stacked over all pairs."""

    pair: np.ndarray  # (N,) index into the pair list
    pix_ref: np.ndarray  # (N, 2)
    pix_src: np.ndarray  # (N, 2)
    plane_n: np.ndarray  # (N, 3) unit normal in the ref depth camera
    plane_d: np.ndarray  # (N,) n . x = d


def _plane_patches(
    pts: np.ndarray, ud: np.ndarray, vd: np.ndarray, half: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Plane fits (normal, offset, rms, all-valid) to (2 half + 1)^2 depth patches."""
    h, w = pts.shape[:2]
    offs = np.arange(-half, half + 1)
    vv = np.clip(vd[:, None, None] + offs[None, :, None], 0, h - 1)
    uu = np.clip(ud[:, None, None] + offs[None, None, :], 0, w - 1)
    patch = pts[vv, uu].reshape(len(ud), (2 * half + 1) ** 2, 3)
    valid = np.asarray((patch[..., 2] > 0).all(axis=1))
    centroid = patch.mean(axis=1)
    centred = patch - centroid[:, None]
    cov = np.einsum("nki,nkj->nij", centred, centred) / patch.shape[1]
    evals, evecs = np.linalg.eigh(cov)
    normal = evecs[:, :, 0]
    rms = np.sqrt(np.maximum(evals[:, 0], 0.0))
    return normal, np.einsum("ni,ni->n", normal, centroid), rms, valid


class _Problem:
    def __init__(
        self,
        pairs: list[_PairData],
        poses: PoseInterpolator,
        K_depth: np.ndarray,
        size_wh: tuple[int, int],
        cfg: ColorCalibrationConfig,
    ) -> None:
        self.pairs, self.poses, self.K_depth, self.cfg = pairs, poses, K_depth, cfg
        self.w, self.h = size_wh
        self.points = [depth_points(p.depth_ref, K_depth) for p in pairs]

    def lift(self, p: np.ndarray) -> _Lifted:
        """Associate every feature with the depth surface behind it at parameters p."""
        cfg, intr = self.cfg, _intrinsics(p, self.w, self.h)
        color_from_depth = _extrinsic(p)
        half = cfg.patch_px // 2
        parts = []
        for k, pair in enumerate(self.pairs):
            colref_from_dref = invert_transform(
                self.poses.at(pair.ref + p[12]) @ invert_transform(color_from_depth)
            ) @ self.poses.at(pair.ref)
            zbuf = render_depth(
                pair.depth_ref, self.K_depth, colref_from_dref, intr, cfg.min_depth_m
            )
            u = np.round(pair.pix_ref[:, 0]).astype(int)
            v = np.round(pair.pix_ref[:, 1]).astype(int)
            inside = (u >= 1) & (u < self.w - 1) & (v >= 1) & (v < self.h - 1)
            u, v = np.clip(u, 1, self.w - 2), np.clip(v, 1, self.h - 2)
            nb = np.stack([zbuf[v + dv, u + du] for dv in (-1, 0, 1) for du in (-1, 0, 1)], 1)
            z = np.median(nb, axis=1)
            good = inside & (nb > 0).all(axis=1)
            good &= (nb.max(axis=1) - nb.min(axis=1)) < 0.03 * np.maximum(z, 1e-3)
            # The colour ray at depth z, in the reference depth camera -> its depth pixel.
            xy = _undistort(p, pair.pix_ref)
            pc = np.concatenate([xy, np.ones((len(xy), 1))], 1) * z[:, None]
            dref_from_colref = invert_transform(colref_from_dref)
            pd = pc @ dref_from_colref[:3, :3].T + dref_from_colref[:3, 3]
            with np.errstate(divide="ignore", invalid="ignore"):
                ud = np.round(self.K_depth[0, 0] * pd[:, 0] / pd[:, 2] + self.K_depth[0, 2])
                vd = np.round(self.K_depth[1, 1] * pd[:, 1] / pd[:, 2] + self.K_depth[1, 2])
            dh, dw = pair.depth_ref.shape
            good &= (ud >= half) & (ud < dw - half) & (vd >= half) & (vd < dh - half)
            ud = np.where(good, ud, half).astype(int)
            vd = np.where(good, vd, half).astype(int)
            normal, d, rms, valid = _plane_patches(self.points[k], ud, vd, half)
            good &= valid & (rms < cfg.max_plane_rms * np.maximum(pd[:, 2], 1e-3))
            # The ray must meet the plane at a decent angle (well-conditioned intersection).
            ray = pd / np.maximum(np.linalg.norm(pd, axis=1, keepdims=True), 1e-9)
            good &= np.abs(np.einsum("ni,ni->n", normal, ray)) > 0.25
            idx = np.nonzero(good)[0]
            parts.append((k, idx, normal[idx], d[idx]))
        return _Lifted(
            pair=np.concatenate([np.full(len(i), k) for k, i, _, _ in parts]),
            pix_ref=np.concatenate([self.pairs[k].pix_ref[i] for k, i, _, _ in parts]),
            pix_src=np.concatenate([self.pairs[k].pix_src[i] for k, i, _, _ in parts]),
            plane_n=np.concatenate([n for _, _, n, _ in parts]),
            plane_d=np.concatenate([d for _, _, _, d in parts]),
        )

    def residuals(self, p: np.ndarray, lifted: _Lifted) -> np.ndarray:
        """Source reprojection errors (2N,) of the lifted features at parameters p."""
        color_from_depth = _extrinsic(p)
        depth_from_color = invert_transform(color_from_depth)
        n = len(lifted.pair)
        # Per pair: depth_ref <- colour_ref and colour_src <- depth_ref.
        a = np.empty((len(self.pairs), 4, 4))
        b = np.empty((len(self.pairs), 4, 4))
        for k, pair in enumerate(self.pairs):
            w_dref = self.poses.at(pair.ref)
            a[k] = invert_transform(w_dref) @ self.poses.at(pair.ref + p[12]) @ depth_from_color
            b[k] = color_from_depth @ invert_transform(self.poses.at(pair.src + p[12])) @ w_dref
        a_n, b_n = a[lifted.pair], b[lifted.pair]
        xy = _undistort(p, lifted.pix_ref)
        ray_c = np.concatenate([xy, np.ones((n, 1))], 1)
        ray_d = np.einsum("nij,nj->ni", a_n[:, :3, :3], ray_c)
        origin = a_n[:, :3, 3]
        denom = np.einsum("ni,ni->n", lifted.plane_n, ray_d)
        s = (lifted.plane_d - np.einsum("ni,ni->n", lifted.plane_n, origin)) / denom
        x_d = origin + s[:, None] * ray_d
        x_s = np.einsum("nij,nj->ni", b_n[:, :3, :3], x_d) + b_n[:, :3, 3]
        z = np.maximum(x_s[:, 2], 1e-3)
        u, v = _distort(p, x_s[:, 0] / z, x_s[:, 1] / z)
        return np.concatenate([u - lifted.pix_src[:, 0], v - lifted.pix_src[:, 1]])


def calibration_pairs(frames: Sequence[int], gap: int) -> list[tuple[int, int]]:
    """Pairs (i, i + gap) with both frames among ``frames``."""
    have = set(frames)
    return [(i, i + gap) for i in frames if i + gap in have]


def calibrate_color_camera(
    source: RgbdSource,
    pairs: Sequence[tuple[int, int]],
    config: ColorCalibrationConfig | None = None,
    progress: bool = False,
) -> ColorCalibration:
    """Estimate the colour camera of ``source`` from colour frame pairs (both directions used).

    Start: focal ``config.initial_focal_px`` at the image centre, no distortion, the colour
    camera at the depth camera (identity), no time offset.
    """
    cfg = config or ColorCalibrationConfig()
    poses = PoseInterpolator(source)
    data: list[_PairData] = []
    cache: dict[int, tuple[np.ndarray, np.ndarray]] = {}

    def load(i: int) -> tuple[np.ndarray, np.ndarray]:
        if i not in cache:
            cache[i] = (cv2.cvtColor(source.color_rgb(i), cv2.COLOR_RGB2GRAY), source.depth_m(i))
        return cache[i]

    for i, j in tqdm(pairs, desc="matching", disable=not progress):
        (gi, di), (gj, dj) = load(i), load(j)
        pa, pb = match_klt(gi, gj, cfg.max_corners)
        data.append(_PairData(i, j, pa, pb, di))
        data.append(_PairData(j, i, pb, pa, dj))
    h, w = next(iter(cache.values()))[0].shape
    problem = _Problem(data, poses, np.asarray(source.K, float), (w, h), cfg)

    f0 = cfg.initial_focal_px
    base = np.array([f0, f0, (w - 1) / 2, (h - 1) / 2, 0, 0, 0, 0, 0, 0, 0, 0, 0], float)
    free = _free_mask(cfg)
    tie = not cfg.separate_focals
    theta = base[free]
    initial_stats: tuple[float, float] | None = None
    lifted = problem.lift(base)
    result = None
    for _ in tqdm(range(cfg.outer_iterations), desc="calibrating", disable=not progress):
        p = _full(theta, base, free, tie)
        lifted = problem.lift(p)
        if initial_stats is None:
            initial_stats = _stats(problem.residuals(p, lifted), cfg.max_reassoc_px)
        result = least_squares(
            lambda t, lf=lifted: problem.residuals(_full(t, base, free, tie), lf),
            theta,
            loss="soft_l1",
            f_scale=cfg.loss_scale_px,
            x_scale="jac",
            max_nfev=200,
        )
        theta = result.x
    p = _full(theta, base, free, tie)
    lifted = problem.lift(p)
    final_res = problem.residuals(p, lifted)
    rms, med = _stats(final_res, cfg.max_reassoc_px)
    std = _parameter_std(problem, lifted, theta, base, free, tie, final_res, cfg.max_reassoc_px)
    assert initial_stats is not None
    return ColorCalibration(
        intrinsics=_intrinsics(p, w, h),
        color_from_depth=_extrinsic(p),
        time_offset_frames=float(p[12]),
        rms_px_initial=initial_stats[0],
        rms_px=rms,
        median_px_initial=initial_stats[1],
        median_px=med,
        num_points=len(lifted.pair),
        std=std,
    )


def _stats(res: np.ndarray, max_px: float) -> tuple[float, float]:
    """(RMS, median) of the point errors (px) below ``max_px``; the median over all points."""
    n = len(res) // 2
    err = np.hypot(res[:n], res[n:])
    inl = err[err < max_px]
    return float(np.sqrt(np.mean(inl**2))) if len(inl) else float("nan"), float(np.median(err))


def _parameter_std(
    problem: _Problem,
    lifted: _Lifted,
    theta: np.ndarray,
    base: np.ndarray,
    free: np.ndarray,
    tie: bool,
    res: np.ndarray,
    max_px: float,
) -> dict[str, float]:
    """1-sigma of the free parameters from J^T J of the inliers (central differences)."""
    n = len(res) // 2
    err = np.hypot(res[:n], res[n:])
    keep = np.tile(err < max_px, 2)
    if keep.sum() <= len(theta):
        return {}
    jac = np.empty((int(keep.sum()), len(theta)))
    for k in range(len(theta)):
        step = 1e-6 * max(1.0, abs(theta[k]))
        tp, tm = theta.copy(), theta.copy()
        tp[k] += step
        tm[k] -= step
        rp = problem.residuals(_full(tp, base, free, tie), lifted)[keep]
        rm = problem.residuals(_full(tm, base, free, tie), lifted)[keep]
        jac[:, k] = (rp - rm) / (2 * step)
    sigma2 = float(np.sum(res[keep] ** 2) / (keep.sum() - len(theta)))
    try:
        cov = np.linalg.inv(jac.T @ jac) * sigma2
    except np.linalg.LinAlgError:
        return {}
    names = [name for name, f in zip(_NAMES, free) if f]
    return {name: float(np.sqrt(max(cov[k, k], 0.0))) for k, name in enumerate(names)}

"""Vectorised ray casting of the synthetic scene into distorted grey camera images.

Per camera, the ray of every *distorted* output pixel is computed once (the exact inverse of
``CameraIntrinsics.project``: OpenCV's undistortion refined by Newton steps), as an unnormalised
direction ``(x_n, y_n, 1)`` in the camera frame, so the ray parameter of a hit *is* the depth z.
Per frame: rotate the rays to the world, intersect the room (slab exit) and the boxes (slab
entry, only over the pixel rectangle each box can cover), turn the hit points into texture
atlas coordinates and sample with ``cv2.remap`` (bilinear) at two mip levels chosen by the
pixel footprint, blended (trilinear filtering, so far surfaces do not alias).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from datasets.synth.scene import Scene
from slam.core.calibration import CameraCalibration, CameraIntrinsics

BAND_ROWS = 48


def pixel_rays(intrinsics: CameraIntrinsics, newton_steps: int = 5) -> np.ndarray:
    """(H, W, 2) normalised undistorted coordinates of every pixel centre, such that
    ``intrinsics.project([x, y, 1])`` returns the pixel to < 1e-6 px."""
    h, w = intrinsics.height, intrinsics.width
    uu, vv = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
    pix = np.stack([uu.ravel(), vv.ravel()], axis=1)
    xy = intrinsics.undistort_points(pix)
    eps = 1e-6
    for _ in range(newton_steps):
        ones = np.ones((len(xy), 1))
        f0 = intrinsics.project(np.hstack([xy, ones])) - pix
        if float(np.abs(f0).max()) < 1e-9:
            break
        fx = (intrinsics.project(np.hstack([xy + [eps, 0.0], ones])) - pix - f0) / eps
        fy = (intrinsics.project(np.hstack([xy + [0.0, eps], ones])) - pix - f0) / eps
        # solve the 2x2 system J d = -f0 per pixel
        a, c = fx[:, 0], fx[:, 1]
        b, d = fy[:, 0], fy[:, 1]
        det = a * d - b * c
        dx = -(d * f0[:, 0] - b * f0[:, 1]) / det
        dy = -(-c * f0[:, 0] + a * f0[:, 1]) / det
        xy = xy + np.stack([dx, dy], axis=1)
    return xy.reshape(h, w, 2)


@dataclass(frozen=True)
class RenderOutput:
    """One camera's image (H, W) uint8 and optional depth (H, W) float32 (z in metres)."""

    image: np.ndarray
    depth_m: np.ndarray | None = None


class CameraRenderer:
    """Renders one camera of a fixed calibration; precomputes its pixel rays."""

    def __init__(self, scene: Scene, camera: CameraCalibration) -> None:
        self.scene = scene
        self.camera = camera
        intr = camera.intrinsics
        self.width, self.height = intr.width, intr.height
        rays_xy = pixel_rays(intr)
        self._xn = np.ascontiguousarray(rays_xy[..., 0], dtype=np.float32)
        self._yn = np.ascontiguousarray(rays_xy[..., 1], dtype=np.float32)
        self._xn_range = (float(rays_xy[..., 0].min()), float(rays_xy[..., 0].max()))
        self._yn_range = (float(rays_xy[..., 1].min()), float(rays_xy[..., 1].max()))
        # footprint: metres per pixel at depth z is about z * |d| / f (before incidence)
        self._ray_len = np.sqrt(self._xn**2 + self._yn**2 + 1.0).astype(np.float32)
        self._tex_x0 = scene.tex_x0.astype(np.float32)
        self._tex_y0 = scene.tex_y0.astype(np.float32)
        self._focal = float(np.sqrt(intr.fx * intr.fy))
        self._box_corners = [
            np.array(
                [
                    [x, y, z]
                    for x in (b.lo_m[0], b.hi_m[0])
                    for y in (b.lo_m[1], b.hi_m[1])
                    for z in (b.lo_m[2], b.hi_m[2])
                ]
            )
            for b in scene.boxes
        ]

    # -------------------------------------------------------------------------------------
    def _box_pixel_rect(
        self, box_index: int, cam_from_world: np.ndarray
    ) -> tuple[int, int, int, int] | None:
        """Pixel rectangle (r0, r1, c0, c1) that can see the box; None if it cannot be seen."""
        corners = self._box_corners[box_index] @ cam_from_world[:3, :3].T + cam_from_world[:3, 3]
        z = corners[:, 2]
        if np.all(z <= 1e-3):
            return None
        if np.any(z <= 0.05):  # partly behind the camera: test every pixel
            return 0, self.height, 0, self.width
        xn = corners[:, 0] / z
        yn = corners[:, 1] / z
        x0, x1 = max(xn.min(), self._xn_range[0]), min(xn.max(), self._xn_range[1])
        y0, y1 = max(yn.min(), self._yn_range[0]), min(yn.max(), self._yn_range[1])
        if x0 > x1 or y0 > y1:
            return None
        # sample the boundary of the (clipped) normalised rectangle: radtan is monotone inside
        # the field of view, but bends straight edges, so corners alone are not enough
        s = np.linspace(0.0, 1.0, 24)
        xs = np.concatenate(
            [x0 + (x1 - x0) * s, np.full_like(s, x1), x0 + (x1 - x0) * s, np.full_like(s, x0)]
        )
        ys = np.concatenate(
            [np.full_like(s, y0), y0 + (y1 - y0) * s, np.full_like(s, y1), y0 + (y1 - y0) * s]
        )
        pix = self.camera.intrinsics.project(np.stack([xs, ys, np.ones_like(xs)], axis=1))
        c0 = int(np.floor(pix[:, 0].min())) - 2
        c1 = int(np.ceil(pix[:, 0].max())) + 3
        r0 = int(np.floor(pix[:, 1].min())) - 2
        r1 = int(np.ceil(pix[:, 1].max())) + 3
        c0, c1 = max(c0, 0), min(c1, self.width)
        r0, r1 = max(r0, 0), min(r1, self.height)
        if c0 >= c1 or r0 >= r1:
            return None
        return r0, r1, c0, c1

    def render(self, world_from_cam: np.ndarray, with_depth: bool = False) -> RenderOutput:
        """Render the grey image (and depth) seen from ``world_from_cam`` (4x4).

        Works in bands of rows so that every temporary array stays in the CPU cache."""
        cam_from_world = np.linalg.inv(world_from_cam)
        rects = [self._box_pixel_rect(b, cam_from_world) for b in range(len(self.scene.boxes))]
        image = np.empty((self.height, self.width), np.uint8)
        depth = np.empty((self.height, self.width), np.float32) if with_depth else None
        for r0 in range(0, self.height, BAND_ROWS):
            r1 = min(r0 + BAND_ROWS, self.height)
            self._render_band(world_from_cam, rects, r0, r1, image, depth)
        return RenderOutput(image=image, depth_m=depth)

    def render_radiance(self, world_from_cam: np.ndarray, band_rows: int = BAND_ROWS) -> np.ndarray:
        """The image as float32 grey levels (not rounded): the radiance a camera model scales.

        ``world_from_cam``: one 4x4 pose, or one per band of ``band_rows`` rows
        (``(ceil(H / band_rows), 4, 4)``, a rolling shutter: each band seen at its own time)."""
        poses = np.asarray(world_from_cam, dtype=np.float64)
        n_bands = -(-self.height // band_rows)
        if poses.ndim == 2:
            poses = np.broadcast_to(poses, (n_bands, 4, 4))
        if poses.shape != (n_bands, 4, 4):
            raise ValueError(f"expected {n_bands} band poses for {band_rows}-row bands")
        rects = self._box_rects_over(poses[0], poses[-1])
        image = np.empty((self.height, self.width), np.float32)
        for b, r0 in enumerate(range(0, self.height, band_rows)):
            r1 = min(r0 + band_rows, self.height)
            self._render_band(poses[b], rects, r0, r1, image, None)
        return image

    def _box_rects_over(
        self, first: np.ndarray, last: np.ndarray
    ) -> list[tuple[int, int, int, int] | None]:
        """Box pixel rectangles covering both poses (the union, widened by 8 px when the poses
        differ: a rolling shutter's bands move a little between its first and last pose)."""
        a = [self._box_pixel_rect(b, np.linalg.inv(first)) for b in range(len(self.scene.boxes))]
        if np.array_equal(first, last):
            return a
        b_ = [self._box_pixel_rect(b, np.linalg.inv(last)) for b in range(len(self.scene.boxes))]
        out: list[tuple[int, int, int, int] | None] = []
        m = 8
        for ra, rb in zip(a, b_):
            if ra is None and rb is None:
                out.append(None)
                continue
            rs = [r for r in (ra, rb) if r is not None]
            out.append(
                (
                    max(min(r[0] for r in rs) - m, 0),
                    min(max(r[1] for r in rs) + m, self.height),
                    max(min(r[2] for r in rs) - m, 0),
                    min(max(r[3] for r in rs) + m, self.width),
                )
            )
        return out

    def render_depth(self, world_from_cam: np.ndarray) -> np.ndarray:
        """Depth only (H, W) float32, z in metres: no texture sampling (about 2x faster)."""
        cam_from_world = np.linalg.inv(world_from_cam)
        rects = [self._box_pixel_rect(b, cam_from_world) for b in range(len(self.scene.boxes))]
        depth = np.empty((self.height, self.width), np.float32)
        for r0 in range(0, self.height, BAND_ROWS):
            r1 = min(r0 + BAND_ROWS, self.height)
            self._render_band(world_from_cam, rects, r0, r1, None, depth)
        return depth

    def _render_band(
        self,
        world_from_cam: np.ndarray,
        rects: list[tuple[int, int, int, int] | None],
        r0: int,
        r1: int,
        image_out: np.ndarray | None,
        depth_out: np.ndarray | None,
    ) -> None:
        scene = self.scene
        f32 = np.float32
        rot = world_from_cam[:3, :3]
        origin = world_from_cam[:3, 3]
        xn = self._xn[r0:r1]
        yn = self._yn[r0:r1]
        d = []
        for k in range(3):
            dk = xn * f32(rot[k, 0])
            dk += yn * f32(rot[k, 1])
            dk += f32(rot[k, 2])
            d.append(dk)
        with np.errstate(divide="ignore"):
            inv = [f32(1.0) / dk for dk in d]

        # room: exit through the nearest plane ahead; the hit face is 2 * axis + (d > 0).
        # Selections are done with arithmetic on 0/1 masks: np.where and boolean indexing
        # are 10-30x slower than a multiply on arrays of this size.
        lo = scene.room.lo_m
        hi = scene.room.hi_m
        t_axis = [
            np.maximum(f32(lo[k] - origin[k]) * inv[k], f32(hi[k] - origin[k]) * inv[k])
            for k in range(3)
        ]
        positive = [dk > 0 for dk in d]
        sel1 = t_axis[1] < t_axis[0]
        t01 = np.minimum(t_axis[0], t_axis[1])
        sel2 = t_axis[2] < t01
        t_best = np.minimum(t01, t_axis[2])
        side = positive[0] ^ (sel1 & (positive[0] ^ positive[1]))
        side ^= sel2 & (side ^ positive[2])
        axis = sel1.astype(np.int8)
        axis += sel2 * (np.int8(2) - axis)
        face = axis.astype(np.int16)
        face *= 2
        face += side

        # boxes: slab entry, only over the pixels that can see each box
        for b, box in enumerate(scene.boxes):
            rect = rects[b]
            if rect is None or rect[1] <= r0 or rect[0] >= r1:
                continue
            a0, a1 = max(rect[0], r0) - r0, min(rect[1], r1) - r0
            c0, c1 = rect[2], rect[3]
            t_near = t_far = ax_near = side_b = None
            for k in range(3):
                ik = inv[k][a0:a1, c0:c1]
                t1 = f32(box.lo_m[k] - origin[k]) * ik
                t2 = f32(box.hi_m[k] - origin[k]) * ik
                tmin = np.minimum(t1, t2)
                tmax = np.maximum(t1, t2)
                neg = ~positive[k][a0:a1, c0:c1]  # entering through the high face
                if t_near is None or t_far is None or ax_near is None or side_b is None:
                    t_near, t_far = tmin, tmax
                    ax_near = np.zeros(tmin.shape, np.int8)
                    side_b = neg
                else:
                    later = tmin > t_near
                    np.maximum(t_near, tmin, out=t_near)
                    ax_near += later * (np.int8(k) - ax_near)
                    side_b = side_b ^ (later & (side_b ^ neg))
                    np.minimum(t_far, tmax, out=t_far)
            assert t_near is not None and t_far is not None
            assert ax_near is not None and side_b is not None
            valid = (t_near <= t_far) & (t_near > 0)
            with np.errstate(divide="ignore", invalid="ignore"):
                # inf or nan where the ray misses the box (fmin and < ignore nan)
                cand = np.maximum(t_near, f32(0.0)) / valid
            tb = t_best[a0:a1, c0:c1]
            hit = cand < tb
            if not hit.any():
                continue
            np.fmin(tb, cand, out=tb)
            ax_s = axis[a0:a1, c0:c1]
            ax_s += hit * (ax_near - ax_s)
            fid = ax_near.astype(np.int16)
            fid *= 2
            fid += side_b
            fid += 6 + 6 * b
            f_s = face[a0:a1, c0:c1]
            f_s += hit * (fid - f_s)
        if depth_out is not None:
            depth_out[r0:r1] = t_best
        if image_out is None:
            return

        # hit points -> atlas coordinates (level 0): u along the first in-plane axis
        # (y for x-walls, else x), v down along the second (z for walls, y for floor/ceiling)
        px = d[0] * t_best
        px += f32(origin[0])
        py = d[1] * t_best
        py += f32(origin[1])
        pz = d[2] * t_best
        pz += f32(origin[2])
        ppm = f32(scene.px_per_m)
        on_x = axis == 0
        on_z = axis == 2
        map_x = py - px
        map_x *= on_x
        map_x += px
        map_x *= ppm
        map_x += np.take(self._tex_x0, face)
        map_y = py - pz
        map_y *= on_z
        map_y += pz
        map_y *= -ppm
        map_y += np.take(self._tex_y0, face)

        # mip level: log2 of texels per pixel footprint, widened for oblique incidence
        d_normal = (d[0] - d[1]) * on_x
        d_normal += (d[2] - d[1]) * on_z
        d_normal += d[1]
        np.abs(d_normal, out=d_normal)
        ray_len = self._ray_len[r0:r1]
        fp2 = t_best * ray_len
        fp2 *= f32(scene.px_per_m / self._focal)
        fp2 *= fp2
        fp2 *= ray_len
        fp2 /= np.maximum(d_normal, f32(0.05) * ray_len)
        np.maximum(fp2, f32(1.0), out=fp2)
        level = np.log2(fp2)
        level *= f32(0.5)
        np.minimum(level, f32(len(scene.atlas_levels) - 1), out=level)
        image_out[r0:r1] = self._sample(map_x, map_y, level, rounded=image_out.dtype == np.uint8)

    def _sample(
        self, map_x: np.ndarray, map_y: np.ndarray, level: np.ndarray, rounded: bool = True
    ) -> np.ndarray:
        """Trilinear sampling: bilinear at each mip level, tent-weighted by ``level``
        (``rounded=False``: float32, not rounded to uint8)."""
        levels = self.scene.atlas_levels
        k_lo = int(np.floor(float(level.min())))
        k_hi = min(int(np.ceil(float(level.max()))), len(levels) - 1)
        out = np.zeros(map_x.shape, np.float32)
        for k in range(k_lo, k_hi + 1):
            scale = np.float32(0.5**k)
            off = np.float32(0.5 * scale - 0.5)  # texel centres of the halved images
            s = cv2.remap(
                levels[k],
                map_x * scale + off if k else map_x,
                map_y * scale + off if k else map_y,
                interpolation=cv2.INTER_LINEAR,
                borderMode=cv2.BORDER_REPLICATE,
            )
            if k_lo == k_hi:
                return s if rounded else s.astype(np.float32)
            w = np.abs(level - np.float32(k))
            np.subtract(np.float32(1.0), w, out=w)
            np.maximum(w, np.float32(0.0), out=w)
            out += w * s
        if not rounded:
            return out
        out += np.float32(0.5)
        return out.astype(np.uint8)


class StereoRenderer:
    """Renders every camera of a calibration at a body pose (world_from_body)."""

    def __init__(self, scene: Scene, cameras: tuple[CameraCalibration, ...]) -> None:
        self.scene = scene
        self.cameras = [CameraRenderer(scene, cam) for cam in cameras]

    def render(self, world_from_body: np.ndarray, with_depth: bool = False) -> list[RenderOutput]:
        return [
            r.render(world_from_body @ r.camera.body_from_cam, with_depth=with_depth)
            for r in self.cameras
        ]

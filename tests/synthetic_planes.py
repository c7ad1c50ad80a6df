"""A tiny ray-cast scene of textured rectangles (a room with a box) with exact depth and surface.

Test helper for dense mapping: images, ground-truth depth (z along the optical axis) and
surface samples are exact, and a 320x240 view renders in a few milliseconds.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np


@dataclass(frozen=True, eq=False)
class Rect:
    """A rectangle origin + s*u + t*v, s in [0, size_u], t in [0, size_v]; u, v orthonormal."""

    origin: np.ndarray
    u: np.ndarray
    v: np.ndarray
    size_u: float
    size_v: float

    @property
    def normal(self) -> np.ndarray:
        return np.cross(self.u, self.v)


def _texture(rng: np.random.Generator, size: int = 512) -> np.ndarray:
    """Multi-scale noise with sharp blobs: textured at every scale a camera sees it."""
    out = np.zeros((size, size), np.float32)
    for sigma, amp in ((1.0, 0.5), (3.0, 1.0), (9.0, 1.5), (27.0, 1.5)):
        n = cv2.GaussianBlur(rng.normal(size=(size, size)).astype(np.float32), (0, 0), sigma)
        out += amp * n / (n.std() + 1e-6)
    out = 128 + 40 * out / out.std()
    return np.clip(out, 0, 255).astype(np.float32)


def _box_rects(lo: np.ndarray, hi: np.ndarray, inward: bool) -> list[Rect]:
    """The 6 faces of an axis-aligned box; normals point inward (a room) or outward (an object)."""
    rects = []
    for axis in range(3):
        a1, a2 = (axis + 1) % 3, (axis + 2) % 3
        e1 = np.eye(3)[a1] * (hi[a1] - lo[a1])
        e2 = np.eye(3)[a2] * (hi[a2] - lo[a2])
        for side, val in ((0, lo[axis]), (1, hi[axis])):
            o = lo.astype(float).copy()
            o[axis] = val
            u, v = e1 / np.linalg.norm(e1), e2 / np.linalg.norm(e2)
            outward = np.eye(3)[axis] * (1 if side else -1)
            flip = (np.dot(np.cross(u, v), outward) < 0) != inward
            if flip:
                u, v = v, u
                rects.append(Rect(o, u, v, float(np.linalg.norm(e2)), float(np.linalg.norm(e1))))
            else:
                rects.append(Rect(o, u, v, float(np.linalg.norm(e1)), float(np.linalg.norm(e2))))
    return rects


class PlaneScene:
    """A room (4 x 3 x 2.5 m, inward faces) with a box on the floor."""

    def __init__(self, seed: int = 0, texel_m: float = 0.004) -> None:
        rng = np.random.default_rng(seed)
        self.rects = _box_rects(np.array([-2.0, -1.5, 0.0]), np.array([2.0, 1.5, 2.5]), True)
        self.rects += _box_rects(np.array([0.2, 0.3, 0.0]), np.array([0.9, 0.9, 0.6]), False)
        self.textures = [_texture(rng) for _ in self.rects]
        self.texel_m = texel_m

    def render(
        self, world_from_cam: np.ndarray, K: np.ndarray, hw: tuple[int, int]
    ) -> tuple[np.ndarray, np.ndarray]:
        """(grey uint8 image, depth float32 z in metres) seen from world_from_cam (x right, y down)."""
        h, w = hw
        v, u = np.mgrid[0:h, 0:w].astype(np.float64)
        d_cam = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)], -1)
        d = d_cam @ world_from_cam[:3, :3].T
        o = world_from_cam[:3, 3]
        best_t = np.full((h, w), np.inf)
        img = np.zeros((h, w), np.float32)
        for rect, tex in zip(self.rects, self.textures):
            n = rect.normal
            denom = d @ n
            with np.errstate(divide="ignore", invalid="ignore"):
                t = ((rect.origin - o) @ n) / denom
            with np.errstate(invalid="ignore"):
                p = o + d * t[..., None]
            s = (p - rect.origin) @ rect.u
            q = (p - rect.origin) @ rect.v
            hit = (t > 1e-3) & (s >= 0) & (s <= rect.size_u) & (q >= 0) & (q <= rect.size_v)
            hit &= t < best_t
            if not hit.any():
                continue
            tx = ((s / self.texel_m) % tex.shape[1]).astype(np.float32)
            ty = ((q / self.texel_m) % tex.shape[0]).astype(np.float32)
            val = cv2.remap(tex, tx, ty, cv2.INTER_LINEAR, borderMode=cv2.BORDER_WRAP)
            img[hit] = val[hit]
            best_t[hit] = t[hit]
        depth = np.where(np.isfinite(best_t), best_t, 0.0).astype(np.float32)  # t = z (d_z = 1)
        return np.clip(img + 0.5, 0, 255).astype(np.uint8), depth

    def sample_surface_points(self, n: int, rng: np.random.Generator) -> np.ndarray:
        """(n, 3) points uniform by area over every rectangle."""
        areas = np.array([r.size_u * r.size_v for r in self.rects])
        which = rng.choice(len(self.rects), size=n, p=areas / areas.sum())
        out = np.empty((n, 3))
        for k, rect in enumerate(self.rects):
            m = which == k
            s = rng.uniform(0, rect.size_u, m.sum())
            t = rng.uniform(0, rect.size_v, m.sum())
            out[m] = rect.origin + s[:, None] * rect.u + t[:, None] * rect.v
        return out

    def distance_to_surface(self, points: np.ndarray) -> np.ndarray:
        """Unsigned distance (m) from points (N, 3) to the nearest rectangle."""
        best = np.full(len(points), np.inf)
        for rect in self.rects:
            rel = points - rect.origin
            s = np.clip(rel @ rect.u, 0, rect.size_u)
            t = np.clip(rel @ rect.v, 0, rect.size_v)
            closest = rect.origin + s[:, None] * rect.u + t[:, None] * rect.v
            best = np.minimum(best, np.linalg.norm(points - closest, axis=1))
        return best


def look_at(eye: np.ndarray, target: np.ndarray) -> np.ndarray:
    """world_from_cam looking from eye to target with world z up (image y down)."""
    z = np.asarray(target, float) - np.asarray(eye, float)
    z /= np.linalg.norm(z)
    x = np.cross(z, [0.0, 0.0, 1.0])
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    out = np.eye(4)
    out[:3, :3] = np.stack([x, y, z], 1)
    out[:3, 3] = eye
    return out


def orbit_poses(n: int, radius: float = 0.6, height: float = 1.3) -> list[np.ndarray]:
    """Cameras on a small circle near the room centre, looking outwards at the walls and box."""
    out = []
    for a in np.linspace(0, 2 * np.pi, n, endpoint=False):
        eye = np.array([radius * np.cos(a) - 0.3, radius * np.sin(a) - 0.2, height])
        target = eye + np.array([np.cos(a), np.sin(a), -0.45])
        out.append(look_at(eye, target))
    return out

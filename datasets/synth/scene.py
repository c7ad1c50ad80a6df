"""The synthetic world: an axis-aligned room (or hall) with a few boxes, every face textured.

Geometry is a set of axis-aligned rectangles ("faces"): the six inner faces of the room and the
six outer faces of each box. Every face owns a rectangle of one texture atlas (a uint8 image
plus a mip pyramid), filled with crops of real photographs shipped by scikit-image (astronaut,
brick, coffee, gravel, ...) arranged in cells of ~300 px, contrast-normalised, with a mild baked
Lambert-like shading from a ceiling light. Different faces get different crops, so places are
distinguishable; ``aliasing=True`` makes all boxes identical and the two long walls identical
(perceptual aliasing for loop-closure tests).

Face ids: room faces ``2 * axis + side`` (side 0 = the plane at the low coordinate), box ``b``
faces ``6 + 6 * b + 2 * axis + side``. Texture coordinates of a point ``p`` on face ``f``:
``atlas_x = tex_x0[f] + tex_cx[f] . p``, ``atlas_y = tex_y0[f] + tex_cy[f] . p`` (atlas pixels,
integer = texel centre, level 0).
"""

from __future__ import annotations

from collections.abc import Sequence as SequenceABC
from dataclasses import dataclass

import cv2
import numpy as np

ROOM_SIZE_M = (8.0, 6.0, 3.0)
HALL_SIZE_M = (30.0, 10.0, 3.0)
PHOTO_NAMES = (
    "astronaut",
    "brick",
    "camera",
    "chelsea",
    "coffee",
    "coins",
    "grass",
    "gravel",
    "hubble_deep_field",
    "immunohistochemistry",
    "moon",
    "page",
    "rocket",
    "text",
    "retina",
    "cell",
    "clock",
)
MIP_LEVELS = 4
GUTTER_PX = 16  # texture padding around each face (>= 2**(MIP_LEVELS-1) * 2)
ATLAS_WIDTH_PX = 8192


@dataclass(frozen=True)
class Box:
    """An axis-aligned box, corners ``lo_m`` < ``hi_m`` (world frame, metres)."""

    lo_m: tuple[float, float, float]
    hi_m: tuple[float, float, float]

    def distance_m(self, points: np.ndarray) -> np.ndarray:
        """Euclidean distance of (N, 3) points to the box (0 inside)."""
        lo = np.asarray(self.lo_m)
        hi = np.asarray(self.hi_m)
        gap = np.maximum(np.maximum(lo - points, points - hi), 0.0)
        return np.linalg.norm(gap, axis=1)

    def contains(self, points: np.ndarray, margin_m: float = 0.0) -> np.ndarray:
        """Whether (N, 3) points are inside the box shrunk by ``margin_m``."""
        lo = np.asarray(self.lo_m) + margin_m
        hi = np.asarray(self.hi_m) - margin_m
        return np.all((points > lo) & (points < hi), axis=1)


@dataclass(frozen=True)
class Face:
    """One textured axis-aligned rectangle.

    ``axis`` is the normal axis, ``plane_m`` its coordinate, ``normal`` points to the side the
    face is seen from. ``u_axis``/``v_axis`` are the in-plane axes with ranges in metres.
    ``owner`` is -1 for the room, else the box index.
    """

    face_id: int
    owner: int
    axis: int
    side: int
    plane_m: float
    normal: tuple[float, float, float]
    u_axis: int
    v_axis: int
    u_range_m: tuple[float, float]
    v_range_m: tuple[float, float]
    atlas_x0: float  # atlas pixel of (u_lo, v_hi), level 0
    atlas_y0: float

    @property
    def area_m2(self) -> float:
        return (self.u_range_m[1] - self.u_range_m[0]) * (self.v_range_m[1] - self.v_range_m[0])

    def corners_m(self) -> np.ndarray:
        """(4, 3) corners, counter-clockwise seen from the visible side."""
        (u0, u1), (v0, v1) = self.u_range_m, self.v_range_m
        pts = np.zeros((4, 3))
        pts[:, self.axis] = self.plane_m
        pts[:, self.u_axis] = [u0, u1, u1, u0]
        pts[:, self.v_axis] = [v0, v0, v1, v1]
        n = np.asarray(self.normal)
        if np.dot(np.cross(pts[1] - pts[0], pts[2] - pts[0]), n) < 0:
            pts = pts[::-1].copy()
        return pts


@dataclass(frozen=True, eq=False)
class Scene:
    """Room + boxes + texture atlas (``atlas_levels[k]`` is level k of the mip pyramid)."""

    room: Box
    boxes: tuple[Box, ...]
    faces: tuple[Face, ...]
    atlas_levels: tuple[np.ndarray, ...]
    px_per_m: float
    tex_x0: np.ndarray  # (F,) float32
    tex_cx: np.ndarray  # (F, 3) float32
    tex_y0: np.ndarray
    tex_cy: np.ndarray

    def surface_faces(self) -> list[Face]:
        """Faces that are actually visible surfaces (drops box bottoms resting on the floor)."""
        floor = self.room.lo_m[2]
        return [
            f
            for f in self.faces
            if not (f.owner >= 0 and f.axis == 2 and f.side == 0 and abs(f.plane_m - floor) < 1e-9)
        ]

    def mesh(self) -> tuple[np.ndarray, np.ndarray]:
        """Vertices (V, 3) float64 and triangles (T, 3) int32 of the true surface, normals
        (by winding, counter-clockwise) pointing to the visible side."""
        faces = self.surface_faces()
        verts = np.concatenate([f.corners_m() for f in faces])
        base = 4 * np.arange(len(faces))[:, None]
        tris = np.concatenate([base + [0, 1, 2], base + [0, 2, 3]]).astype(np.int32)
        return verts, tris

    def sample_surface_points(
        self, n: int, seed: int = 0, return_normals: bool = False
    ) -> np.ndarray | tuple[np.ndarray, np.ndarray]:
        """``n`` points uniformly (by area) on the visible surface; optionally their normals."""
        rng = np.random.default_rng(seed)
        faces = self.surface_faces()
        areas = np.array([f.area_m2 for f in faces])
        which = rng.choice(len(faces), size=n, p=areas / areas.sum())
        pts = np.zeros((n, 3))
        normals = np.zeros((n, 3))
        uv = rng.random((n, 2))
        for k, f in enumerate(faces):
            m = which == k
            pts[m, f.axis] = f.plane_m
            pts[m, f.u_axis] = f.u_range_m[0] + uv[m, 0] * (f.u_range_m[1] - f.u_range_m[0])
            pts[m, f.v_axis] = f.v_range_m[0] + uv[m, 1] * (f.v_range_m[1] - f.v_range_m[0])
            normals[m] = f.normal
        return (pts, normals) if return_normals else pts

    def clearance_m(self, points: np.ndarray) -> np.ndarray:
        """Distance of (N, 3) points (inside the room) to the nearest wall or box surface;
        negative when outside the room or inside a box."""
        lo = np.asarray(self.room.lo_m)
        hi = np.asarray(self.room.hi_m)
        d = np.minimum(points - lo, hi - points).min(axis=1)
        for b in self.boxes:
            inside = b.contains(points)
            db = b.distance_m(points)
            d = np.minimum(d, np.where(inside, -1.0, db))
        return d


def load_photos() -> list[np.ndarray]:
    """Grey float32 [0, 1] versions of scikit-image's bundled sample photographs."""
    import skimage.data
    from skimage.color import rgb2gray, rgba2rgb

    photos = []
    for name in PHOTO_NAMES:
        img = getattr(skimage.data, name)()
        if img.ndim == 3 and img.shape[2] == 4:
            img = rgba2rgb(img)
        if img.ndim == 3:
            img = rgb2gray(img)
        img = np.asarray(img, dtype=np.float32)
        if img.max() > 1.5:
            img = img / 255.0
        photos.append(img)
    left, _right, _disp = skimage.data.stereo_motorcycle()
    photos.append(np.asarray(rgb2gray(left), dtype=np.float32))
    return photos


def _cell_texture(
    rng: np.random.Generator, photos: list[np.ndarray], w_px: int, h_px: int
) -> np.ndarray:
    """One cell: a random crop of a random photo, random flips/transpose, contrast-normalised."""
    photo = photos[int(rng.integers(len(photos)))]
    if rng.random() < 0.5:
        photo = photo.T
    scale = float(rng.uniform(0.7, 1.5))  # photo pixels per texture pixel
    cw = max(2, round(w_px * scale))
    ch = max(2, round(h_px * scale))
    ph, pw = photo.shape
    if ch > ph or cw > pw:  # mirror-tile small photos up to the crop size
        photo = np.pad(photo, ((0, max(0, ch - ph)), (0, max(0, cw - pw))), mode="symmetric")
        ph, pw = photo.shape
    y0 = int(rng.integers(0, ph - ch + 1))
    x0 = int(rng.integers(0, pw - cw + 1))
    crop = photo[y0 : y0 + ch, x0 : x0 + cw]
    if rng.random() < 0.5:
        crop = crop[:, ::-1]
    if rng.random() < 0.5:
        crop = crop[::-1, :]
    cell = cv2.resize(np.ascontiguousarray(crop), (w_px, h_px), interpolation=cv2.INTER_AREA)
    std = float(cell.std())
    mean = float(rng.uniform(0.38, 0.62))
    contrast = float(rng.uniform(0.15, 0.22))
    return np.clip((cell - cell.mean()) / (std + 1e-3) * contrast + mean, 0.02, 0.98)


def _face_texture(
    rng: np.random.Generator, photos: list[np.ndarray], w_px: int, h_px: int, cell_px: int
) -> np.ndarray:
    """A face texture (h_px, w_px) float32 built from a grid of photo cells."""
    n_cols = max(1, round(w_px / cell_px))
    n_rows = max(1, round(h_px / cell_px))
    xs = np.linspace(0, w_px, n_cols + 1).round().astype(int)
    ys = np.linspace(0, h_px, n_rows + 1).round().astype(int)
    tex = np.zeros((h_px, w_px), dtype=np.float32)
    for r in range(n_rows):
        for c in range(n_cols):
            tex[ys[r] : ys[r + 1], xs[c] : xs[c + 1]] = _cell_texture(
                rng, photos, xs[c + 1] - xs[c], ys[r + 1] - ys[r]
            )
    return tex


def _make_faces_geometry(room: Box, boxes: SequenceABC[Box]) -> list[dict]:
    """Plane, normal and in-plane ranges of every face (no texture placement yet)."""
    out = []
    owners: list[tuple[int, Box]] = [(-1, room)] + list(enumerate(boxes))
    for owner, box in owners:
        lo, hi = np.asarray(box.lo_m), np.asarray(box.hi_m)
        for axis in range(3):
            u_axis, v_axis = ((1, 2), (0, 2), (0, 1))[axis]
            for side in (0, 1):
                plane = float(lo[axis] if side == 0 else hi[axis])
                sign = 1.0 if side == 0 else -1.0  # room faces look inward
                if owner >= 0:
                    sign = -sign  # box faces look outward
                normal = [0.0, 0.0, 0.0]
                normal[axis] = sign
                out.append(
                    dict(
                        owner=owner,
                        axis=axis,
                        side=side,
                        plane_m=plane,
                        normal=tuple(normal),
                        u_axis=u_axis,
                        v_axis=v_axis,
                        u_range_m=(float(lo[u_axis]), float(hi[u_axis])),
                        v_range_m=(float(lo[v_axis]), float(hi[v_axis])),
                    )
                )
    return out


def _shade(face: dict, room: Box, w_px: int, h_px: int, px_per_m: float) -> np.ndarray:
    """Mild baked lighting: a soft ceiling light at the room centre, Lambert-like falloff."""
    lo, hi = np.asarray(room.lo_m), np.asarray(room.hi_m)
    light = np.array([(lo[0] + hi[0]) / 2, (lo[1] + hi[1]) / 2, hi[2] - 0.2])
    us = face["u_range_m"][0] + np.arange(w_px) / px_per_m
    vs = face["v_range_m"][1] - np.arange(h_px) / px_per_m
    scale2 = float(np.sum((hi - lo) ** 2)) / 4.0
    # exp(-|p - light|^2 / s) separates into a product over the three axes
    fu = np.exp(-((us - light[face["u_axis"]]) ** 2) / scale2).astype(np.float32)
    fv = np.exp(-((vs - light[face["v_axis"]]) ** 2) / scale2).astype(np.float32)
    fn = np.float32(np.exp(-((face["plane_m"] - light[face["axis"]]) ** 2) / scale2))
    out = np.multiply.outer(fv * (np.float32(0.3) * fn), fu)
    out += np.float32(0.7)
    return out


def _paint_marker(tex: np.ndarray, x_px: float, y_px: float, radius_px: float) -> None:
    """A white disc on a black square (for geometry tests), in place."""
    h, w = tex.shape
    half = 2.2 * radius_px
    r0, r1 = max(0, int(np.floor(y_px - half))), min(h, int(np.ceil(y_px + half)) + 1)
    c0, c1 = max(0, int(np.floor(x_px - half))), min(w, int(np.ceil(x_px + half)) + 1)
    yy, xx = np.mgrid[r0:r1, c0:c1]
    r = np.sqrt((xx - x_px) ** 2 + (yy - y_px) ** 2)
    # black square, anti-aliased white disc (so the rendered centroid is unbiased)
    tex[r0:r1, c0:c1] = np.clip(radius_px + 0.5 - r, 0.0, 1.0)


def candidate_boxes(room: Box, kind: str, rng: np.random.Generator, aliasing: bool) -> list[Box]:
    """Boxes on a coarse grid of the floor (before removing those near the path)."""
    lo, hi = np.asarray(room.lo_m), np.asarray(room.hi_m)
    centre = (lo + hi) / 2
    half = (hi - lo) / 2
    fx: tuple[float, ...]
    fy: tuple[float, ...]
    if kind == "hall":
        fx = (-0.85, -0.55, -0.25, 0.0, 0.25, 0.55, 0.85)
        fy = (-0.8, 0.0, 0.8)
    else:
        fx = (-0.8, 0.0, 0.8)
        fy = (-0.78, 0.0, 0.78)
    boxes = []
    for ax in fx:
        for ay in fy:
            if aliasing:
                hx, hy, h = 0.4, 0.4, 1.0
            else:
                hx, hy = rng.uniform(0.25, 0.5, size=2)
                h = rng.uniform(0.5, min(2.0, 0.8 * (hi[2] - lo[2])))
            cx, cy = centre[0] + ax * half[0], centre[1] + ay * half[1]
            boxes.append(
                Box(
                    (float(cx - hx), float(cy - hy), float(lo[2])),
                    (float(cx + hx), float(cy + hy), float(lo[2] + h)),
                )
            )
    return boxes


def build_scene(
    kind: str = "room",
    *,
    room: Box | None = None,
    path_m: np.ndarray | None = None,
    clearance_m: float = 0.7,
    max_boxes: int = 6,
    aliasing: bool = False,
    seed: int = 0,
    px_per_m: float | None = None,
    markers_m: SequenceABC[SequenceABC[float]] = (),
    marker_radius_m: float = 0.03,
) -> Scene:
    """Build a textured room (``kind="room"``, 8x6x3 m) or hall (``"hall"``, 30x10x3 m).

    ``path_m`` (N, 3): camera/body positions to keep boxes away from (boxes closer than
    ``clearance_m`` are dropped). ``markers_m``: world points on faces painted as white discs on
    black squares (for geometry tests). The scene (textures, boxes) depends only on ``seed``.
    """
    rng = np.random.default_rng(seed)
    if room is None:
        size = np.asarray(HALL_SIZE_M if kind == "hall" else ROOM_SIZE_M)
        room = Box(
            (float(-size[0] / 2), float(-size[1] / 2), 0.0),
            (float(size[0] / 2), float(size[1] / 2), float(size[2])),
        )
    if px_per_m is None:
        area = 2 * sum(
            a * b
            for a, b in (
                (room.hi_m[0] - room.lo_m[0], room.hi_m[1] - room.lo_m[1]),
                (room.hi_m[0] - room.lo_m[0], room.hi_m[2] - room.lo_m[2]),
                (room.hi_m[1] - room.lo_m[1], room.hi_m[2] - room.lo_m[2]),
            )
        )
        px_per_m = float(np.clip(np.sqrt(16e6 / area), 64.0, 256.0))  # <= ~16 Mpx of texture
    cell_px = 300
    boxes = candidate_boxes(room, kind, rng, aliasing)
    if path_m is not None and len(path_m):
        keep = [b for b in boxes if float(b.distance_m(path_m).min()) >= clearance_m]
    else:
        keep = list(boxes)
    order = rng.permutation(len(keep))
    boxes = [keep[i] for i in sorted(order[:max_boxes])]

    geo = _make_faces_geometry(room, boxes)
    photos = load_photos()
    # texture keys: faces sharing a key share an atlas rectangle (perceptual aliasing)
    keys: list[tuple] = []
    for g in geo:
        if aliasing and g["owner"] >= 0:
            keys.append(("box", g["axis"], g["side"]))
        elif aliasing and g["owner"] < 0 and g["axis"] == 1:
            keys.append(("long-wall",))
        else:
            keys.append(("face", len(keys)))
    unique: dict[tuple, int] = {}
    for i, k in enumerate(keys):
        unique.setdefault(k, i)

    # shelf-pack unique textures into the atlas
    sizes = {}
    for k, i in unique.items():
        g = geo[i]
        w = int(np.ceil((g["u_range_m"][1] - g["u_range_m"][0]) * px_per_m)) + 1
        h = int(np.ceil((g["v_range_m"][1] - g["v_range_m"][0]) * px_per_m)) + 1
        sizes[k] = (w, h)
    order_keys = sorted(sizes, key=lambda k: -sizes[k][1])
    placement: dict[tuple, tuple[int, int]] = {}
    x = y = shelf_h = 0
    for k in order_keys:
        w, h = sizes[k][0] + 2 * GUTTER_PX, sizes[k][1] + 2 * GUTTER_PX
        if w > ATLAS_WIDTH_PX:
            raise ValueError("a face is too large for the texture atlas; lower px_per_m")
        if x + w > ATLAS_WIDTH_PX:
            x, y, shelf_h = 0, y + shelf_h, 0
        placement[k] = (x, y)
        x += w
        shelf_h = max(shelf_h, h)
    align = 2 ** (MIP_LEVELS - 1)
    atlas_h = int(np.ceil((y + shelf_h) / align) * align)
    atlas_w = ATLAS_WIDTH_PX if y > 0 else int(np.ceil(x / align) * align)
    atlas = np.zeros((atlas_h, atlas_w), dtype=np.uint8)

    gains = rng.uniform(0.8, 1.1, size=len(unique))
    for n, (k, i) in enumerate(unique.items()):
        g = geo[i]
        w, h = sizes[k]
        tex = _face_texture(rng, photos, w, h, cell_px) * gains[n]
        tex *= _shade(g, room, w, h, px_per_m)
        for m in markers_m:
            p = np.asarray(m, dtype=float)
            on_plane = abs(p[g["axis"]] - g["plane_m"]) < 1e-6
            inside = (
                g["u_range_m"][0] <= p[g["u_axis"]] <= g["u_range_m"][1]
                and g["v_range_m"][0] <= p[g["v_axis"]] <= g["v_range_m"][1]
            )
            if on_plane and inside:
                _paint_marker(
                    tex,
                    (p[g["u_axis"]] - g["u_range_m"][0]) * px_per_m,
                    (g["v_range_m"][1] - p[g["v_axis"]]) * px_per_m,
                    marker_radius_m * px_per_m,
                )
        tex *= np.float32(255.0)
        tex += np.float32(0.5)
        padded = np.pad(np.clip(tex, 0, 255).astype(np.uint8), GUTTER_PX, mode="symmetric")
        x0, y0 = placement[k]
        atlas[y0 : y0 + padded.shape[0], x0 : x0 + padded.shape[1]] = padded
    levels = [atlas]
    for _ in range(1, MIP_LEVELS):
        prev = levels[-1]
        levels.append(
            cv2.resize(prev, (prev.shape[1] // 2, prev.shape[0] // 2), interpolation=cv2.INTER_AREA)
        )

    faces = []
    n_f = len(geo)
    tex_x0 = np.zeros(n_f, np.float64)
    tex_y0 = np.zeros(n_f, np.float64)
    tex_cx = np.zeros((n_f, 3), np.float64)
    tex_cy = np.zeros((n_f, 3), np.float64)
    for i, g in enumerate(geo):
        px, py = placement[keys[i]]
        ax0, ay0 = float(px + GUTTER_PX), float(py + GUTTER_PX)
        faces.append(Face(face_id=i, atlas_x0=ax0, atlas_y0=ay0, **g))
        tex_cx[i, g["u_axis"]] = px_per_m
        tex_x0[i] = ax0 - g["u_range_m"][0] * px_per_m
        tex_cy[i, g["v_axis"]] = -px_per_m
        tex_y0[i] = ay0 + g["v_range_m"][1] * px_per_m
    return Scene(
        room=room,
        boxes=tuple(boxes),
        faces=tuple(faces),
        atlas_levels=tuple(levels),
        px_per_m=px_per_m,
        tex_x0=tex_x0,
        tex_cx=tex_cx,
        tex_y0=tex_y0,
        tex_cy=tex_cy,
    )


def room_around_path(path_m: np.ndarray, margin_m: float = 2.0, min_height_m: float = 3.0) -> Box:
    """A room enclosing a path with ``margin_m`` to the walls (and >= 0.8 m above/below)."""
    lo = path_m.min(axis=0)
    hi = path_m.max(axis=0)
    z_lo = lo[2] - max(0.8, (min_height_m - (hi[2] - lo[2])) / 2)
    z_hi = hi[2] + max(0.8, (min_height_m - (hi[2] - lo[2])) / 2)
    return Box(
        (float(lo[0] - margin_m), float(lo[1] - margin_m), float(z_lo)),
        (float(hi[0] + margin_m), float(hi[1] + margin_m), float(z_hi)),
    )

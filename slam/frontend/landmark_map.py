"""The front end's map of landmarks it no longer tracks, and the search that finds them again.

Why: the front end tracks landmarks frame to frame and forgets one when its track ends, so a
place seen again got new landmarks, and the odometry drifted through it. Here every landmark
keeps its best position (the back end's, as published in its estimates), where and how it was
first seen, and the patch it was born with. At each keyframe, :meth:`LandmarkMap.search`
projects the untracked ones that the predicted camera should see, and looks for each with its
birth patch warped into the current view (SVO's affine warp from the birth view, fronto-parallel
at the landmark; NCC over a small window, then the inverse-compositional affine fit of
:mod:`slam.frontend.affine_klt`). The caller checks the matches together (one PnP) before it
tracks them again. Hand-written because OpenCV has no projection-guided patch search; ORB-SLAM's
descriptor search needs a descriptor per frame, which the KLT front end does not compute.

Frames: positions and birth geometry are in the front end's world (the back end's after its
initialisation); a landmark is only searched in its own map segment.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from slam.core.calibration import CameraIntrinsics
from slam.frontend.affine_klt import (
    AffineTemplates,
    build_templates,
    empty_templates,
    refine_affine,
    sample_image,
)

PATCH_HALF_PX = 9  # the stored birth patch is (2 * 9 + 1)^2: the affine template (+-7) and margin


def cut_patches(image: np.ndarray, px: np.ndarray) -> np.ndarray:
    """(N, 19, 19) float32 patches of ``image`` centred on the sub-pixel points ``px`` (N, 2)."""
    r = np.arange(-PATCH_HALF_PX, PATCH_HALF_PX + 1, dtype=np.float32)
    yy, xx = np.meshgrid(r, r, indexing="ij")
    pts = np.asarray(px, np.float32).reshape(-1, 2)
    side = 2 * PATCH_HALF_PX + 1
    xs = pts[:, 0:1] + xx.ravel()[None]
    ys = pts[:, 1:2] + yy.ravel()[None]
    return sample_image(image, xs, ys).reshape(-1, side, side)


def templates_from_patches(patches: np.ndarray, half_window_px: int) -> AffineTemplates:
    """Affine templates of stored patches (N, 19, 19): one mosaic, one ``build_templates``."""
    n, side = len(patches), 2 * PATCH_HALF_PX + 1
    mosaic = np.ascontiguousarray(np.asarray(patches, np.float32).reshape(n * side, side))
    centres = np.stack(
        [
            np.full(n, PATCH_HALF_PX, np.float32),
            PATCH_HALF_PX + side * np.arange(n, dtype=np.float32),
        ],
        axis=1,
    )
    return build_templates(mosaic, centres, half_window_px)


@dataclass(frozen=True)
class MapMatches:
    """Landmarks found again in one image: ``ids`` (M,), ``pixels`` (M, 2) distorted,
    ``positions_world`` (M, 3), ``templates`` their birth patches' affine templates and
    ``linear`` (M, 2, 2) the fitted warps (to carry on tracking with), ``candidates``: how
    many untracked landmarks the camera should have seen (the revisit's size)."""

    ids: np.ndarray
    pixels: np.ndarray
    positions_world: np.ndarray
    templates: AffineTemplates
    linear: np.ndarray
    candidates: int

    def take(self, index: np.ndarray) -> MapMatches:
        return MapMatches(
            self.ids[index],
            self.pixels[index],
            self.positions_world[index],
            self.templates.take(index),
            self.linear[index],
            self.candidates,
        )

    @staticmethod
    def none(candidates: int, half_window_px: int) -> MapMatches:
        return MapMatches(
            np.zeros(0, np.int64),
            np.zeros((0, 2)),
            np.zeros((0, 3)),
            empty_templates(half_window_px),
            np.zeros((0, 2, 2), np.float32),
            candidates,
        )


@dataclass(frozen=True)
class SearchParams:
    radius_px: int
    min_ncc: float
    max_candidates: int
    max_view_angle_deg: float
    max_scale_change: float
    half_window_px: int
    max_rms: float
    unique_exclusion_px: int = 2  # no rival peak farther than this from the best (Chebyshev)


# the per-landmark arrays of a LandmarkMap, one row per landmark
_COLUMNS = (
    "ids",
    "pos",
    "refined",
    "tracked",
    "segment",
    "birth_centre",
    "pixel_step",
    "patch",
    "last_seen",
    "birth_kf",
)


class LandmarkMap:
    """Landmarks by id: position, refined (the back end estimated it), segment, birth camera
    centre, the world displacement of one pixel along the birth image's x and y at the
    landmark, the birth patch, and whether the front end tracks it now. Only refined
    landmarks are searched (with a back end; without one, the front end's are all there is).

    Rows live in growing arrays with an id -> row index; ``capacity`` bounds them (the least
    recently seen are dropped first)."""

    def __init__(self, capacity: int) -> None:
        self.capacity = capacity
        self._row: dict[int, int] = {}
        self._n = 0
        side = 2 * PATCH_HALF_PX + 1
        self.ids = np.zeros(0, np.int64)
        self.pos = np.zeros((0, 3))
        self.refined = np.zeros(0, bool)
        self.tracked = np.zeros(0, bool)
        self.segment = np.zeros(0, np.int64)
        self.birth_centre = np.zeros((0, 3))
        self.pixel_step = np.zeros((0, 2, 3))  # world displacement of +1 px in x, y at birth
        self.patch = np.zeros((0, side, side), np.float32)
        self.last_seen = np.zeros(0, np.int64)  # search counter
        self.birth_kf = np.zeros(0, np.int64)  # keyframe id
        self._clock = 0

    def __len__(self) -> int:
        return self._n

    def _grow(self, extra: int) -> None:
        need = self._n + extra
        if need <= len(self.ids):
            return
        size = max(need, 2 * len(self.ids), 256)

        def grown(a: np.ndarray) -> np.ndarray:
            out = np.zeros((size,) + a.shape[1:], a.dtype)
            out[: self._n] = a[: self._n]
            return out

        for name in _COLUMNS:
            setattr(self, name, grown(getattr(self, name)))

    def rows(self, ids: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(found mask over ``ids``, their rows)."""
        rows = np.array([self._row.get(int(i), -1) for i in np.asarray(ids).tolist()], np.int64)
        found = rows >= 0
        return found, rows[found]

    def add(
        self,
        ids: np.ndarray,
        positions_world: np.ndarray,
        px: np.ndarray,
        image: np.ndarray,
        world_from_cam: np.ndarray,
        intrinsics: CameraIntrinsics,
        segment: int,
        keyframe_id: int,
        refined: bool = False,
    ) -> None:
        """New landmarks born at ``px`` (distorted) in ``image`` of keyframe ``keyframe_id``,
        seen from ``world_from_cam``."""
        ids = np.asarray(ids, np.int64)
        if len(ids) == 0:
            return
        self._make_room(len(ids))
        self._grow(len(ids))
        sl = slice(self._n, self._n + len(ids))
        pos = np.asarray(positions_world, float).reshape(-1, 3)
        rot, centre = world_from_cam[:3, :3], world_from_cam[:3, 3]
        depth = (pos - centre) @ rot[:, 2]
        self.ids[sl] = ids
        self.pos[sl] = pos
        self.refined[sl] = refined
        self.tracked[sl] = True
        self.segment[sl] = segment
        self.birth_centre[sl] = centre
        self.pixel_step[sl, 0] = (depth / intrinsics.fx)[:, None] * rot[:, 0]
        self.pixel_step[sl, 1] = (depth / intrinsics.fy)[:, None] * rot[:, 1]
        self.patch[sl] = cut_patches(image, px)
        self.last_seen[sl] = self._clock
        self.birth_kf[sl] = keyframe_id
        for r, lid in enumerate(ids.tolist()):
            self._row[lid] = self._n + r
        self._n += len(ids)

    def _make_room(self, extra: int) -> None:
        """Drop the least recently seen untracked landmarks when ``capacity`` would be passed."""
        if self._n + extra <= self.capacity:
            return
        n = self._n
        order = np.argsort(
            self.last_seen[:n] + np.where(self.tracked[:n], 1 << 40, 0), kind="stable"
        )
        drop = order[: max(self._n + extra - int(0.8 * self.capacity), 0)]
        keep = np.setdiff1d(np.arange(n), drop)
        for name in _COLUMNS:
            setattr(self, name, getattr(self, name)[keep].copy())
        self._n = len(keep)
        self._row = {int(lid): r for r, lid in enumerate(self.ids[: self._n].tolist())}

    def update_positions(self, ids: np.ndarray, positions_world: np.ndarray) -> None:
        """The back end's estimates of these landmarks (they become searchable)."""
        found, rows = self.rows(ids)
        if len(rows):
            self.pos[rows] = np.asarray(positions_world, float).reshape(-1, 3)[found]
            self.refined[rows] = True

    def transform(self, new_from_old: np.ndarray) -> None:
        """A change of frame of the whole map (the back end's world adopted)."""
        n = self._n
        rot, trans = new_from_old[:3, :3], new_from_old[:3, 3]
        self.pos[:n] = self.pos[:n] @ rot.T + trans
        self.birth_centre[:n] = self.birth_centre[:n] @ rot.T + trans
        self.pixel_step[:n] = self.pixel_step[:n] @ rot.T

    def scale(self, factor: float) -> None:
        """Scale the whole map about the world origin (a monocular map made metric)."""
        n = self._n
        self.pos[:n] *= factor
        self.birth_centre[:n] *= factor
        self.pixel_step[:n] *= factor

    def retire(self, ids: np.ndarray, positions_world: np.ndarray) -> None:
        """Landmarks the front end stopped tracking, at their last known positions (a
        position the back end refined stays refined)."""
        found, rows = self.rows(ids)
        if len(rows):
            self.pos[rows] = np.asarray(positions_world, float).reshape(-1, 3)[found]
            self.tracked[rows] = False
            self.last_seen[rows] = self._clock

    def anchor_keyframe(self, ids: np.ndarray) -> int:
        """The keyframe most of these landmarks were born at (-1 for none)."""
        _, rows = self.rows(ids)
        if len(rows) == 0:
            return -1
        kfs, counts = np.unique(self.birth_kf[rows], return_counts=True)
        return int(kfs[np.argmax(counts)])

    def mark_tracked(self, ids: np.ndarray) -> None:
        """Landmarks found again: tracked from now on."""
        _, rows = self.rows(ids)
        self.tracked[rows] = True
        self.last_seen[rows] = self._clock

    def search(
        self,
        image: np.ndarray,
        world_from_cam: np.ndarray,
        intrinsics: CameraIntrinsics,
        segment: int,
        params: SearchParams,
    ) -> MapMatches:
        """Untracked, refined landmarks of ``segment`` the camera should see, looked for in
        ``image``; the matches are not yet checked against each other."""
        self._clock += 1
        n = self._n
        empty = MapMatches.none(0, params.half_window_px)
        cand = np.flatnonzero(self.refined[:n] & ~self.tracked[:n] & (self.segment[:n] == segment))
        if len(cand) == 0:
            return empty
        rot, centre = world_from_cam[:3, :3], world_from_cam[:3, 3]
        pos = self.pos[cand]
        pc = (pos - centre) @ rot
        margin = params.radius_px + PATCH_HALF_PX + 2
        ok = pc[:, 2] > 0.1
        cand, pos, pc = cand[ok], pos[ok], pc[ok]
        if len(cand) == 0:
            return empty
        uv = intrinsics.project(pc)
        # seen from a similar direction and distance as at birth (the patch still looks alike)
        now_ray = pos - centre
        birth_ray = pos - self.birth_centre[cand]
        d_now, d_birth = np.linalg.norm(now_ray, axis=1), np.linalg.norm(birth_ray, axis=1)
        cos = np.sum(now_ray * birth_ray, axis=1) / np.maximum(d_now * d_birth, 1e-9)
        scale = d_birth / np.maximum(d_now, 1e-9)
        ok = (
            (uv[:, 0] >= margin)
            & (uv[:, 1] >= margin)
            & (uv[:, 0] < intrinsics.width - margin)
            & (uv[:, 1] < intrinsics.height - margin)
            & (cos > np.cos(np.radians(params.max_view_angle_deg)))
            & (scale < params.max_scale_change)
            & (scale > 1.0 / params.max_scale_change)
        )
        cand, pos, uv = cand[ok], pos[ok], uv[ok]
        n_cand = len(cand)
        if n_cand == 0:
            return empty
        if n_cand > params.max_candidates:  # spread over the image: a coarse grid, round robin
            cell = (uv[:, 1] // 60).astype(np.int64) * 1000 + (uv[:, 0] // 60).astype(np.int64)
            order = np.lexsort((-self.last_seen[cand], cell))
            rank = np.zeros(len(cand), np.int64)
            cells = cell[order]
            starts = np.r_[0, np.flatnonzero(np.diff(cells)) + 1]
            for s, e in zip(starts, np.r_[starts[1:], len(cells)], strict=True):
                rank[order[s:e]] = np.arange(e - s)
            pick = np.argsort(rank, kind="stable")[: params.max_candidates]
            cand, pos, uv = cand[pick], pos[pick], uv[pick]
        # predicted warp birth patch -> image: where one birth pixel step lands now
        lin = np.empty((len(cand), 2, 2))
        for axis in (0, 1):
            moved = (pos + self.pixel_step[cand, axis] - centre) @ rot
            moved[:, 2] = np.maximum(moved[:, 2], 1e-6)
            lin[:, :, axis] = intrinsics.project(moved) - uv
        return self._match(image, cand, uv, lin, n_cand, params)

    def _match(
        self,
        image: np.ndarray,
        cand: np.ndarray,
        uv: np.ndarray,
        lin: np.ndarray,
        n_cand: int,
        params: SearchParams,
    ) -> MapMatches:
        r = params.radius_px
        side = 2 * PATCH_HALF_PX + 1
        size = 2 * r + side
        c = (size - 1) / 2.0
        det = lin[:, 0, 0] * lin[:, 1, 1] - lin[:, 0, 1] * lin[:, 1, 0]
        use = np.flatnonzero(np.isfinite(det) & (det > 0.1) & (det <= 10))
        if len(use) == 0:
            return MapMatches.none(n_cand, params.half_window_px)
        a = lin[use].astype(np.float64)
        p = uv[use].astype(np.float64)
        warp = np.concatenate([a, (p - a @ np.array([c, c]))[:, :, None]], axis=2)
        patches = self.patch[cand[use]]
        n_side = 2 * r + 1
        best = np.full(len(use), -np.inf)
        x0 = np.zeros(len(use), np.int64)
        y0 = np.zeros(len(use), np.int64)
        # one matchTemplate per landmark: a batched FFT correlation with integral-image
        # normalisation was twice as slow in numpy
        for k in range(len(use)):
            region = cv2.warpAffine(
                image,
                warp[k],
                (size, size),
                flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
                borderMode=cv2.BORDER_REPLICATE,
            )
            score = cv2.matchTemplate(region.astype(np.float32), patches[k], cv2.TM_CCOEFF_NORMED)
            _, top, _, (x, y) = cv2.minMaxLoc(score)
            if top < params.min_ncc:
                continue
            # unique: nothing else in the window nearly as good (repeated texture); the peak's
            # own slopes, within unique_exclusion_px of it, are no rival
            e = params.unique_exclusion_px
            if n_side * n_side > (2 * e + 1) ** 2:
                score[max(y - e, 0) : y + e + 1, max(x - e, 0) : x + e + 1] = -1.0
                if float(score.max()) > top - 0.1:
                    continue
            best[k], x0[k], y0[k] = top, x, y
        keep = np.flatnonzero(np.isfinite(best))
        if len(keep) == 0:
            return MapMatches.none(n_cand, params.half_window_px)
        offset = np.stack([x0[keep] - r, y0[keep] - r], axis=1).astype(np.float64)
        found_px = p[keep] + (a[keep] @ offset[:, :, None])[:, :, 0]
        rows = cand[use[keep]]
        templ = templates_from_patches(self.patch[rows], params.half_window_px)
        fit = refine_affine(
            templ,
            image,
            found_px.astype(np.float32),
            a[keep].astype(np.float32),
            iterations=6,
            max_shift_px=2.0,
            max_rms=params.max_rms,
            min_ncc=0.0,  # the patch search's NCC (params.min_ncc) and uniqueness checked it
        )
        ok = np.flatnonzero(fit.ok)
        return MapMatches(
            self.ids[rows[ok]].copy(),
            fit.pts_px[ok].astype(float),
            self.pos[rows[ok]].copy(),
            templ.take(ok),
            fit.linear[ok],
            n_cand,
        )

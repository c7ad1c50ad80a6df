"""The monocular front end: one camera, landmarks triangulated from motion.

Beside the stereo :class:`~slam.frontend.tracker.FrontEnd` (same KLT, affine re-fit, PnP,
keyframe decisions and map reuse); what differs is where landmarks come from:

- **Start (two-view structure from motion).** A reference frame's corners are tracked by KLT.
  While their median displacement stays under ``mono_init_min_parallax_px`` the state is
  "waiting for motion" (no pose). Then an essential matrix (OpenCV RANSAC), ``recoverPose``
  and triangulation of its inliers; the start is accepted only with ``mono_init_min_points``
  points in front of both views, reprojecting within ``mono_max_reprojection_px``, with a
  median ray angle of at least ``mono_init_min_angle_deg`` (a pure rotation fails here: its
  rays are parallel). Until the back end's visual-inertial alignment has fixed the scale, the
  map's unit is a guess (median depth ``mono_init_depth_m``) and poses are not published.
- **New landmarks.** Corners detected at a keyframe are candidates, tracked like landmarks;
  at each later keyframe a candidate is triangulated from its first view and the current one
  (linear two-view, batched) once their rays differ by ``mono_min_angle_deg`` and both
  reprojections are within ``mono_max_reprojection_px``; after
  ``mono_candidate_max_keyframes`` keyframes without that it is dropped.
- **Scale.** The back end's first initialised :class:`Estimate` carries ``vo_scale``: the map
  (landmarks, poses, the landmark map) is scaled by it about the VO origin before the change
  of frame into the back end's metric, gravity-aligned world is applied as in stereo.
- **After a loss** the start is redone; once in the back end's world, the new map takes its
  scale and pose from IMU dead reckoning between the two views (the segment continues),
  else it starts a new segment.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np

from slam.config import FrontendConfig
from slam.core.calibration import Calibration
from slam.core.geometry import invert_transform, make_transform, scale_body_pose
from slam.core.messages import Estimate, Keyframe, StereoFrame, TrackingResult
from slam.frontend.features import detect_features, essential_ransac, track_klt
from slam.frontend.tracker import MAX_STORED_KEYFRAME_POSES, FrontEnd
from slam.imu_buffer import ImuBuffer

MONO_LANDMARK_GATE = 0.1
WAITING = "waiting for motion"
INITIALISING = "initialising"


@dataclass
class _Reference:
    """The first view of a two-view start: its corners, where they are now, its pose."""

    t_ns: int
    px0: np.ndarray  # (N, 2) float32 at the reference frame
    px: np.ndarray  # (N, 2) float32 tracked to the latest frame
    world_from_body: np.ndarray


def triangulate_two_view(
    cam_a_from_world: np.ndarray,
    cam_b_from_world: np.ndarray,
    rays_a: np.ndarray,
    rays_b: np.ndarray,
) -> np.ndarray:
    """Linear (DLT) triangulation of N points, each from its own pair of views: ``cam_*`` are
    (N, 4, 4) or (4, 4), ``rays_*`` (N, 2) normalised image coordinates. Returns (N, 3) world
    points (NaN where degenerate). Batched numpy SVD: OpenCV's ``triangulatePoints`` takes one
    pair of projection matrices for all points, and candidates are born at different keyframes."""
    n = len(rays_a)
    pa = np.broadcast_to(cam_a_from_world[..., :3, :], (n, 3, 4))
    pb = np.broadcast_to(cam_b_from_world[..., :3, :], (n, 3, 4))
    a = np.stack(
        [
            rays_a[:, 0, None] * pa[:, 2] - pa[:, 0],
            rays_a[:, 1, None] * pa[:, 2] - pa[:, 1],
            rays_b[:, 0, None] * pb[:, 2] - pb[:, 0],
            rays_b[:, 1, None] * pb[:, 2] - pb[:, 1],
        ],
        axis=1,
    )
    _, _, vt = np.linalg.svd(a)
    h = vt[:, -1]
    with np.errstate(divide="ignore", invalid="ignore"):
        pts = h[:, :3] / h[:, 3:4]
    pts[np.abs(h[:, 3]) < 1e-12] = np.nan
    return pts


def _reprojection_px(cam_from_world: np.ndarray, pts: np.ndarray, rays: np.ndarray, f: float):
    """(pixel error, depth) of points against normalised observations (batched poses ok)."""
    pc = (
        np.einsum("...ij,...j->...i", cam_from_world[..., :3, :3], pts) + cam_from_world[..., :3, 3]
    )
    z = pc[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        err = np.linalg.norm(pc[:, :2] / z[:, None] - rays, axis=1) * f
    return np.where(np.isfinite(err), err, np.inf), z


def _ray_angle_deg(
    world_from_cam_a: np.ndarray, world_from_cam_b: np.ndarray, pts: np.ndarray
) -> np.ndarray:
    """Angle at each point between the two viewing rays, degrees."""
    da = pts - world_from_cam_a[..., :3, 3]
    db = pts - world_from_cam_b[..., :3, 3]
    cos = np.sum(da * db, axis=1) / (np.linalg.norm(da, axis=1) * np.linalg.norm(db, axis=1))
    return np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))


class MonoFrontEnd(FrontEnd):
    """Monocular visual tracking (module docstring); the back end fixes the scale."""

    monocular = True

    def __init__(
        self,
        calib: Calibration,
        cfg: FrontendConfig,
        imu: ImuBuffer | None = None,
        estimate_source: Callable[[], Estimate | None] | None = None,
        relocaliser: Any = None,
    ):
        super().__init__(calib, cfg, imu, estimate_source, relocaliser)
        self._source = self.estimate_source
        self._gate_cache: tuple[Estimate, Estimate] | None = None
        if estimate_source is not None:
            self.estimate_source = self._gated_estimate
        self._ref: _Reference | None = None
        self._next_candidate = -2  # candidates have ids <= -2; landmarks >= 0; -1 unused
        # candidate id -> (normalised ray at its first view (2,), keyframe born at); only the
        # candidates still tracked (pruned at each keyframe)
        self._cand: dict[int, tuple[np.ndarray, int]] = {}
        # keyframe id -> its cam_from_world (4, 4), for the keyframes candidates were born at:
        # one pose per keyframe, not one per candidate, to move with the map
        self._cand_cam_from_world: dict[int, np.ndarray] = {}
        self.scale_adopted = 1.0
        self._wait_state = ""

    # ------------------------------------------------------------------ feedback
    def _gated_estimate(self) -> Estimate | None:
        """The back end's estimate with only the landmark positions that agree with ours
        (within ``MONO_LANDMARK_GATE`` of their distance from the camera): a monocular smart
        factor's point from a short baseline can be far off in depth, and a few of them
        adopted as our landmarks pull PnP away."""
        est = self._source()
        if est is None or not est.initialized or not len(est.landmark_ids):
            return est
        cached = self._gate_cache
        if cached is not None and cached[0] is est:
            return cached[1]
        ids = est.landmark_ids.tolist()
        ours = np.array([self.landmarks.get(i, (np.nan, np.nan, np.nan)) for i in ids], float)
        theirs = np.asarray(est.landmark_positions_world, float)
        centre = (
            (self.world_from_body @ self.body_from_cam0)[:3, 3]
            if self.world_from_body is not None
            else np.zeros(3)
        )
        dist = np.linalg.norm(ours - centre, axis=1)
        with np.errstate(invalid="ignore"):
            ok = np.linalg.norm(theirs - ours, axis=1) <= MONO_LANDMARK_GATE * dist
        # (landmarks we no longer track pass: the landmark map keeps the back end's)
        ok |= ~np.isfinite(ours).all(axis=1)
        gated = dataclasses.replace(
            est, landmark_ids=est.landmark_ids[ok], landmark_positions_world=theirs[ok]
        )
        self._gate_cache = (est, gated)
        return gated

    # ------------------------------------------------------------------ scale
    def _adopt_scale(self, est: Estimate, fe_pose: np.ndarray) -> np.ndarray:
        s = float(est.vo_scale)
        if s == 1.0 or not np.isfinite(s) or s <= 0:
            return fe_pose
        b = self.body_from_cam0
        for lid in self.landmarks:
            self.landmarks[lid] = self.landmarks[lid] * s
        for kid in self.kf_poses:
            self.kf_poses[kid] = scale_body_pose(self.kf_poses[kid], s, b)
        for name in ("world_from_body", "prev_world_from_body"):
            pose = getattr(self, name)
            if pose is not None:
                setattr(self, name, scale_body_pose(pose, s, b))
        self.last_known_pose = scale_body_pose(self.last_known_pose, s, b)
        for kf, cam_from_world in self._cand_cam_from_world.items():
            world_from_cam = invert_transform(cam_from_world)
            world_from_cam[:3, 3] *= s
            self._cand_cam_from_world[kf] = invert_transform(world_from_cam)
        self.landmark_map.scale(s)
        self._prior_cache = None
        self.scale_adopted = s
        self.stats.state_log.append((est.t_ns, f"map scaled by {s:.4f} (metres per VO unit)"))
        return scale_body_pose(fe_pose, s, b)

    def _move_world(self, correction: np.ndarray) -> None:
        """As the stereo front end's, and the candidates' first views and the reference move
        with the map (a triangulation mixes them with the current pose)."""
        super()._move_world(correction)
        old_from_new = invert_transform(correction)
        for kf, cam_from_world in self._cand_cam_from_world.items():
            self._cand_cam_from_world[kf] = cam_from_world @ old_from_new
        if self._ref is not None:
            self._ref.world_from_body = correction @ self._ref.world_from_body

    # ------------------------------------------------------------------ start
    def _normalised(self, px: np.ndarray) -> np.ndarray:
        return self.cam0.undistort_points(px).reshape(-1, 2)

    def _waiting(
        self, frame: StereoFrame, t_start: float, state: str, reason: str
    ) -> TrackingResult:
        """A frame without a pose while the map cannot start (logged when the state changes)."""
        if state != self._wait_state:
            self._wait_state = state
            self.stats.state_log.append((frame.t_ns, f"{state}: {reason}"))
        return self._result(frame, state, t_start, reason=reason)

    def _new_reference(self, frame: StereoFrame) -> None:
        px = detect_features(frame.left, np.zeros((0, 2), np.float32), self.cfg)
        pose = self._imu_prior(frame.t_ns) if self.reframed else None
        self._ref = _Reference(
            frame.t_ns,
            px.astype(np.float32),
            px.astype(np.float32).copy(),
            pose if pose is not None else self.last_known_pose.copy(),
        )

    def _start_segment(
        self, frame: StereoFrame, pyr: np.ndarray, t_start: float
    ) -> tuple[TrackingResult, Keyframe | None]:
        cfg = self.cfg
        self.px = np.zeros((0, 2), np.float32)
        self.ids = np.zeros(0, np.int64)
        self.ages = np.zeros(0, np.int64)
        self._retire(list(self.landmarks))
        self._cand.clear()
        self._cand_cam_from_world.clear()
        self._anchor_kf = -1
        self.templates.clear()
        ref = self._ref
        if ref is None or self.pyr_prev is None:
            self._new_reference(frame)
            return self._waiting(frame, t_start, WAITING, "reference frame taken"), None
        px, ok = track_klt(self.pyr_prev, pyr, ref.px, cfg)
        ref.px0, ref.px = ref.px0[ok], px[ok]
        if len(ref.px) < cfg.mono_init_min_points:
            self._new_reference(frame)
            return self._waiting(frame, t_start, WAITING, "reference lost: new reference"), None
        parallax = float(np.median(np.linalg.norm(ref.px - ref.px0, axis=1)))
        if parallax < cfg.mono_init_min_parallax_px:
            return self._waiting(frame, t_start, WAITING, f"parallax {parallax:.1f} px"), None
        made = self._two_view(frame, ref)
        if made is None:
            return self._waiting(frame, t_start, INITIALISING, "two-view check failed"), None
        pts_world, keep, world_from_body, continues = made
        self.world_from_body = world_from_body
        self.prev_world_from_body = None
        ids = np.arange(self.next_landmark_id, self.next_landmark_id + len(pts_world))
        self.next_landmark_id += len(ids)
        self.px = ref.px[keep].astype(np.float32)
        self.ids = ids.astype(np.int64)
        self.ages = np.zeros(len(ids), np.int64)
        for lid, p in zip(ids.tolist(), pts_world, strict=True):
            self.landmarks[lid] = p
        world_from_cam = world_from_body @ self.body_from_cam0
        self.landmark_map.add(
            ids,
            pts_world,
            self.px,
            frame.left,
            world_from_cam,
            self.cam0,
            self.segment_id if continues else self.segment_id + 1,
            self.next_keyframe_id,
            refined=not self.has_backend,
        )
        if cfg.affine_refinement:
            self.templates.add(ids, self.px, frame.left)
        self._ref = None
        self._wait_state = ""
        kf = self._make_keyframe(frame, pyr, new_segment=not continues)
        assert kf is not None
        self.stats.tracked += 1
        self.last_known_pose = world_from_body
        self.mapped = True
        reason = f"two views {(frame.t_ns - ref.t_ns) * 1e-9:.2f} s apart, {len(ids)} points"
        self.stats.state_log.append((frame.t_ns, f"monocular map started: {reason}"))
        return (
            self._result(
                frame,
                "recovered" if continues else "init",
                t_start,
                world_from_body=world_from_body if self.reframed else None,
                is_keyframe=True,
                keyframe_id=kf.keyframe_id,
                num_inliers=len(ids),
                reason=reason,
            ),
            kf,
        )

    def _two_view(
        self, frame: StereoFrame, ref: _Reference
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, bool] | None:
        """Essential matrix, relative pose and triangulation between the reference and this
        frame: (world points, rows of ref.px they belong to, world_from_body now, whether the
        scale and pose came from the IMU), or None when the checks fail."""
        cfg = self.cfg
        n0, n1 = self._normalised(ref.px0), self._normalised(ref.px)
        f = float(self.cam0.fx)
        found = essential_ransac(n0, n1, cfg.mono_max_reprojection_px / f)
        if found is None:
            return None
        e_mat, mask = found
        _, rot, t, mask = cv2.recoverPose(e_mat, n0, n1, np.eye(3), mask=mask.copy())
        c1_from_c0 = make_transform(rot, t.ravel())
        inl = np.flatnonzero(mask.ravel() > 0)
        if len(inl) < cfg.mono_init_min_points:
            return None
        c0 = np.eye(4)
        pts = triangulate_two_view(c0, c1_from_c0, n0[inl], n1[inl])
        e0, z0 = _reprojection_px(c0, pts, n0[inl], f)
        e1, z1 = _reprojection_px(c1_from_c0, pts, n1[inl], f)
        angle = _ray_angle_deg(c0, invert_transform(c1_from_c0), pts)
        good = (
            (z0 > 0) & (z1 > 0) & (e0 < cfg.mono_max_reprojection_px)
            & (e1 < cfg.mono_max_reprojection_px) & np.isfinite(pts).all(axis=1)
        )  # fmt: skip
        if good.sum() < cfg.mono_init_min_points:
            return None
        if float(np.median(angle[good])) < cfg.mono_init_min_angle_deg:
            return None
        good &= angle > 0.25 * cfg.mono_init_min_angle_deg
        scale = cfg.mono_init_depth_m / float(np.median(z0[good]))
        world_from_cam_ref = ref.world_from_body @ self.body_from_cam0
        continues = False
        if self.reframed and self.imu is not None:
            now = self._imu_prior(frame.t_ns)
            if now is not None:
                c_ref = world_from_cam_ref[:3, 3]
                c_now = (now @ self.body_from_cam0)[:3, 3]
                moved = float(np.linalg.norm(c_now - c_ref))
                if moved > 0.02:
                    scale, continues = moved, True  # the unit baseline becomes the IMU's
        c0_from_c1 = invert_transform(c1_from_c0)
        c0_from_c1[:3, 3] *= scale
        world_from_cam_now = world_from_cam_ref @ c0_from_c1
        pts_world = (pts[good] * scale) @ world_from_cam_ref[:3, :3].T + world_from_cam_ref[:3, 3]
        return pts_world, inl[good], world_from_cam_now @ self.cam0_from_body, continues

    # ------------------------------------------------------------------ tracking
    def _track(self, frame: StereoFrame, pyr: np.ndarray, t_start: float) -> TrackingResult:
        result = super()._track(frame, pyr, t_start)
        if not self.reframed and result.world_from_body is not None:
            # up to scale until the back end has aligned it with the IMU: not a pose to publish
            self.stats.tracked -= 1
            return dataclasses.replace(result, world_from_body=None, state=INITIALISING)
        return result

    # ------------------------------------------------------------------ keyframes
    def _need_keyframe(self, t_ns: int, num_inliers: int) -> bool:
        """As the stereo front end's, and before the scale is known a keyframe at least every
        ``mono_init_keyframe_interval_s`` (the start's alignment needs keyframes over time)."""
        every_s = self.cfg.mono_init_keyframe_interval_s
        if not self.reframed and every_s > 0 and (t_ns - self.kf_t_ns) * 1e-9 >= every_s:
            return True
        return super()._need_keyframe(t_ns, num_inliers)

    def _make_keyframe(
        self, frame: StereoFrame, pyr: np.ndarray, new_segment: bool = False
    ) -> Keyframe | None:
        assert self.world_from_body is not None
        cfg = self.cfg
        self._revisit = False
        if cfg.map_reuse and self.mapped and not new_segment and self.reframed:
            self._reuse_map(frame)
        kf_id = self.next_keyframe_id
        world_from_cam = self.world_from_body @ self.body_from_cam0
        cam_from_world = invert_transform(world_from_cam)
        self._triangulate_candidates(frame, cam_from_world, world_from_cam, kf_id)
        new_px = detect_features(frame.left, self.px, cfg).astype(np.float32)
        cids = np.arange(self._next_candidate, self._next_candidate - len(new_px), -1)
        self._next_candidate -= len(new_px)
        rays = self._normalised(new_px) if len(new_px) else np.zeros((0, 2))
        for cid, ray in zip(cids.tolist(), rays, strict=True):
            self._cand[cid] = (ray, kf_id)
        if len(new_px):
            self._cand_cam_from_world[kf_id] = cam_from_world
        self.px = np.vstack([self.px, new_px]).astype(np.float32)
        self.ids = np.concatenate([self.ids, cids.astype(np.int64)])
        self.ages = np.concatenate([self.ages, np.zeros(len(new_px), np.int64)])
        if new_segment:
            self.segment_id += 1
            self.stats.segments += 1
            self.stats.state_log.append((frame.t_ns, f"map segment {self.segment_id} started"))
        self.next_keyframe_id += 1
        self.stats.keyframes += 1
        self.kf_t_ns = frame.t_ns
        has_lm = np.array([i in self.landmarks for i in self.ids.tolist()], dtype=bool)
        lm_ids = self.ids[has_lm]
        self.kf_px = {int(i): p for i, p in zip(lm_ids, self.px[has_lm], strict=True)}
        self.kf_num_landmarks = int(has_lm.sum())
        self.kf_poses[kf_id] = self.world_from_body.copy()
        if len(self.kf_poses) > MAX_STORED_KEYFRAME_POSES:
            del self.kf_poses[min(self.kf_poses)]
        und = self._undistorted_px(self.px[has_lm]) if has_lm.any() else np.zeros((0, 2))
        return Keyframe(
            t_ns=frame.t_ns,
            keyframe_id=kf_id,
            frame_index=frame.index,
            segment_id=self.segment_id,
            world_from_body_vo=self.world_from_body.copy(),
            landmark_ids=lm_ids.copy(),
            pixels_left_undist=und,
            pixels_right_undist=np.full_like(und, np.nan),
            points_world_vo=np.array([self.landmarks[i] for i in lm_ids.tolist()]).reshape(-1, 3),
            image_left=frame.left,
            image_right=None,
            metric=self.reframed,
        )

    def _triangulate_candidates(
        self,
        frame: StereoFrame,
        cam_from_world: np.ndarray,
        world_from_cam: np.ndarray,
        kf_id: int,
    ) -> None:
        """Candidates seen with enough parallax become landmarks (module docstring); those
        whose tracks were lost since the last keyframe are forgotten."""
        cfg = self.cfg
        rows = np.flatnonzero(self.ids <= -2)
        keep = np.ones(len(self.ids), dtype=bool)
        cids = self.ids[rows].tolist()
        self._cand = {c: self._cand[c] for c in cids}
        if len(rows) == 0:
            self._cand_cam_from_world.clear()
            return
        births = [self._cand[c] for c in cids]
        born = np.array([b[1] for b in births])
        born_at, which = np.unique(born, return_inverse=True)
        cam_at = np.array([self._cand_cam_from_world[k] for k in born_at.tolist()])
        cam_a = cam_at[which]
        rays_a = np.array([b[0] for b in births])
        age = kf_id - born
        rays_b = self._normalised(self.px[rows])
        pts = triangulate_two_view(cam_a, cam_from_world, rays_a, rays_b)
        f = float(self.cam0.fx)
        ea, za = _reprojection_px(cam_a, pts, rays_a, f)
        eb, zb = _reprojection_px(cam_from_world, pts, rays_b, f)
        world_from_cam_a = np.array([invert_transform(c) for c in cam_at])[which]
        angle = _ray_angle_deg(world_from_cam_a, world_from_cam, pts)
        fits = (za > 0) & (zb > 0) & (ea < cfg.mono_max_reprojection_px)
        fits &= (eb < cfg.mono_max_reprojection_px) & np.isfinite(pts).all(axis=1)
        made = fits & (angle >= cfg.mono_min_angle_deg)
        # a track that cannot fit two views once they are far apart is a bad track
        bad = ~fits & (angle >= 2 * cfg.mono_min_angle_deg)
        too_old = ~made & (age >= cfg.mono_candidate_max_keyframes)
        keep[rows[bad | too_old]] = False
        new_rows = rows[made]
        new_ids = np.arange(self.next_landmark_id, self.next_landmark_id + len(new_rows))
        self.next_landmark_id += len(new_ids)
        for r, lid, p in zip(new_rows.tolist(), new_ids.tolist(), pts[made], strict=True):
            del self._cand[int(self.ids[r])]
            self.ids[r] = lid
            self.landmarks[lid] = p
        for r in rows[~keep[rows]].tolist():
            self._cand.pop(int(self.ids[r]), None)
        alive = {kf for _, kf in self._cand.values()}
        self._cand_cam_from_world = {
            k: c for k, c in self._cand_cam_from_world.items() if k in alive
        }
        if len(new_ids):
            self.landmark_map.add(
                new_ids,
                pts[made],
                self.px[new_rows],
                frame.left,
                world_from_cam,
                self.cam0,
                self.segment_id,
                kf_id,
                refined=not self.has_backend,
            )
            if cfg.affine_refinement:
                self.templates.add(new_ids, self.px[new_rows], frame.left)
        self.px, self.ids, self.ages = self.px[keep], self.ids[keep], self.ages[keep]
        if cfg.affine_refinement:
            self.templates.keep_only(self.ids[self.ids >= 0])

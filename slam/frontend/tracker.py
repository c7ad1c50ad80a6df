"""The front end: every frame, track features, estimate the pose, decide keyframes.

Per frame: black/textureless check -> gyro-predicted KLT (forward-backward checked) -> a
quarter of the landmark tracks re-fitted to their birth patch (``affine_klt``) -> PnP
RANSAC against the local map's landmarks (+ LM refinement) -> keyframe decision -> at keyframes,
new grid-bucketed features and stereo triangulation of new landmarks.

The front end never waits for the back end: it reads the latest published :class:`Estimate`
through a callable and re-anchors its local map to it (the correction between the back end's
and its own pose of the same keyframe is applied to the current pose and unrefined landmarks).

Tracking loss (too few PnP inliers, a black or textureless frame) leaves a gap in the trajectory;
the next usable frame starts a new map segment from stereo, at the last known pose.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import cv2
import numpy as np

from slam.config import FrontendConfig
from slam.core.calibration import Calibration
from slam.core.geometry import (
    invert_transform,
    is_rigid,
    make_transform,
    nearest_rigid,
    rotation_angle_rad,
    skew_batch,
    so3_exp,
    so3_log,
    transform_points,
)
from slam.core.messages import Estimate, FrontendCorrection, Keyframe, StereoFrame, TrackingResult
from slam.cputime import runqueue_wait_ns, thread_cpu_s
from slam.frontend.affine_klt import TrackTemplates
from slam.frontend.features import (
    ReducedImages,
    brightness_ratio,
    build_pyramid,
    detect_features,
    match_brightness,
    track_klt,
)
from slam.frontend.landmark_map import LandmarkMap, MapMatches, SearchParams
from slam.frontend.motion_blur import BlurBound, blur_length_px, rate_turn
from slam.frontend.stereo import StereoMatcher
from slam.imu_buffer import ImuBuffer, integrate_gyro, propagate_pose

MAX_STORED_KEYFRAME_POSES = 200


@dataclass
class FrontendStats:
    frames: int = 0
    tracked: int = 0
    lost_frames: int = 0
    tracking_losses: int = 0
    segments: int = 0
    relocalisations: int = 0
    imu_bridged: int = 0
    keyframes: int = 0
    blur_pose_fused: int = 0
    """Frames whose PnP pose was fused with the IMU's prediction for their predicted motion
    blur (``blur_pose_prior_min_px``)."""
    estimate_corrections: int = 0
    map_rescales: int = 0
    """Monocular: times the map was scaled to the back end's landmarks
    (``mono_map_rescale_tolerance``)."""
    klt_predicted: int = 0
    """Tracks started at their landmark's projection from the predicted pose
    (``klt_predicted_levels``)..."""
    klt_retracked: int = 0
    """Tracks lost from a bad prediction, tracked again over the full pyramid."""
    track_refits: int = 0
    """Affine re-fits of tracks to their birth patch attempted (``affine_klt``)..."""
    track_refits_kept: int = 0
    """...and kept (the others were weak, moved too far or degenerated)."""
    state_log: list[tuple[int, str]] = field(default_factory=list)
    map_searches: int = 0
    """Keyframes at which untracked landmarks of the map were searched (map reuse)..."""
    map_candidates: int = 0
    """...landmarks the camera should have seen there, summed..."""
    map_found: int = 0
    """...found again by their patch, summed..."""
    map_reobserved: int = 0
    """...and kept after the check against each other (PnP), summed."""
    map_rejected: int = 0
    """Searches whose matches disagreed with the tracked pose by more than
    ``map_max_correction_m`` / ``_deg`` (a false revisit) or among themselves."""
    map_corrections: int = 0
    """Searches that moved the local map onto the older landmarks."""
    map_correction_max_m: float = 0.0
    landmark_frames: int = 0
    """Frames tracked with landmarks, and the landmarks they tracked (PnP inliers)..."""
    landmarks_tracked: int = 0
    landmarks_tracked_old: int = 0
    """...of which found again in the map."""
    revisit_frames: int = 0
    """Frames after a keyframe whose search had at least ``map_min_inliers`` candidates, and
    their landmarks (PnP inliers), all and found again."""
    revisit_landmarks: int = 0
    revisit_landmarks_old: int = 0
    after_pose_ms: list[float] = field(default_factory=list)
    """Wall time of each frame's work after its pose was published (:meth:`FrontEnd.after_pose`:
    keyframe creation, new landmarks' templates), ms."""


class FrontEnd:
    """Stereo visual tracking with an optional gyro prior and back-end feedback (the
    monocular front end, ``slam.frontend.mono.MonoFrontEnd``, is a subclass)."""

    monocular = False

    def __init__(
        self,
        calib: Calibration,
        cfg: FrontendConfig,
        imu: ImuBuffer | None = None,
        estimate_source: Callable[[], Estimate | None] | None = None,
        relocaliser: Any = None,
    ):
        if not calib.is_stereo and not self.monocular:
            raise ValueError("the front end needs a stereo calibration (cam0 and cam1)")
        self.calib = calib
        self.cfg = cfg
        self.imu = imu
        self.has_backend = estimate_source is not None
        self.estimate_source = estimate_source or (lambda: None)
        self.corrections: list[FrontendCorrection] = []
        """Corrections applied since the owner last took them (:meth:`take_corrections`)."""
        self.relocaliser = relocaliser  # slam.loop.relocaliser.Relocaliser, or None
        self.reframed = False
        self.restarts_adopted = 0  # the back end's monocular restarts whose scale we took
        self.cam0 = calib.cameras[0].intrinsics
        self.K = self.cam0.K
        self.body_from_cam0 = calib.cameras[0].body_from_cam
        self.cam0_from_body = invert_transform(self.body_from_cam0)
        self.stereo = StereoMatcher(calib, cfg) if calib.is_stereo else None
        self.stats = FrontendStats()
        # tracks
        self.px = np.zeros((0, 2), np.float32)
        self.ids = np.zeros(0, np.int64)
        self.ages = np.zeros(0, np.int64)
        self.landmarks: dict[int, np.ndarray] = {}
        self.landmark_map = LandmarkMap(cfg.map_max_landmarks)
        self.reobserved_ids: set[int] = set()  # tracked ids found again in the map
        self._revisit = False  # the last keyframe's search saw enough of the map
        self._anchor_kf = -1  # birth keyframe of the old landmarks this frame is tracked on
        self.templates = TrackTemplates(
            cfg.affine_half_window_px, cfg.affine_iterations, cfg.affine_min_ncc
        )
        self.pyr_prev: np.ndarray | None = None
        self.reduced = ReducedImages()  # brightness_ratio's reduced images
        self.t_prev_ns = 0
        # pose state
        self.world_from_body: np.ndarray | None = None  # last tracked pose
        self.prev_world_from_body: np.ndarray | None = None
        self.prev_dt_ns = 0
        self.last_known_pose = np.eye(4)
        self.segment_id = -1
        self.mapped = False
        # keyframes
        self.next_landmark_id = 0
        self.next_keyframe_id = 0
        self.kf_t_ns = 0
        self.kf_px: dict[int, np.ndarray] = {}
        self.kf_num_landmarks = 0
        self.kf_poses: dict[int, np.ndarray] = {}
        self.applied_estimate: tuple[int, int] = (-1, -1)
        self.bias_gyro = np.zeros(3)
        self.latest_estimate: Estimate | None = None
        self._prior_cache: tuple[Estimate, int, np.ndarray, np.ndarray] | None = None
        self._keyframe_due: tuple[StereoFrame, np.ndarray] | None = None
        self._keyframe_made: Keyframe | None = None
        # the current frame's predicted motion blur, px (motion_blur.py); where it is at most
        # blur_pose_prior_min_px, possibly an upper bound of it (_predicted_blur)
        self.blur_px = 0.0
        self._px_normalised: np.ndarray | None = None  # _tracks_normalised, this frame's
        self._blur_bound = (
            BlurBound(self.cam0) if cfg.blur_pose_prior_min_px > 0 and imu is not None else None
        )  # _predicted_blur's; made here, not in a frame (~5 ms)
        self._cpu_start_s = 0.0  # thread CPU time and run-queue wait when track() started
        self._runqueue_start_ns: int | None = None
        self.gravity_m_s2 = calib.imu.gravity_m_s2 if calib.imu else 9.81

    # ------------------------------------------------------------------ feedback
    def take_corrections(self) -> list[FrontendCorrection]:
        """The corrections applied since the last call (for the stages that follow them)."""
        out, self.corrections = self.corrections, []
        return out

    def _apply_estimate(self) -> None:
        est = self.estimate_source()
        if est is None or not est.initialized:
            return
        key = (est.keyframe_id, est.map_generation)
        if key == self.applied_estimate:
            return
        fe_pose = self.kf_poses.get(est.keyframe_id)
        if not self.reframed:
            # The first initialised estimate is in the back end's gravity-aligned world; we are
            # in the VO frame until its change of frame is applied, which needs our pose of its
            # keyframe (tracking or not). Until then nothing of it is adopted: as the IMU prior
            # it restarted tracking after a loss at a world pose among VO-frame poses.
            if fe_pose is None:
                return
            if not self._rigid_estimate(est, fe_pose):
                self.applied_estimate = key
                return
        self.applied_estimate = key
        self.latest_estimate = est
        self.bias_gyro = np.asarray(est.bias_gyro_rad_s, dtype=float)
        if self.imu is not None and est.imu_intrinsics is not None:
            self.imu.set_intrinsics(est.imu_intrinsics)  # the back end's biases are for these
        if fe_pose is None or (self.reframed and not self.mapped):
            return
        if not self._rigid_estimate(est, fe_pose):
            return
        # a monocular back end that redid its start (``Estimate.restarts``) has a new scale for
        # our map, already in its world: scaled again, and moved to its estimate as below
        restarted = self.reframed and est.restarts != self.restarts_adopted
        if not self.reframed or restarted:
            fe_pose = self._adopt_scale(est, fe_pose)
            self.restarts_adopted = est.restarts
        correction = nearest_rigid(est.world_from_body @ invert_transform(fe_pose))
        self.stats.estimate_corrections += 1
        # The first initialised estimate moves us from the VO frame (the first body pose)
        # into the back end's gravity-aligned world: a change of frame, not a correction, so
        # everything already output must move with it (``reframe``).
        if not self.reframed or restarted:
            self.landmark_map.transform(correction)
        self.corrections.append(FrontendCorrection(est.t_ns, correction, not self.reframed))
        self.reframed = True
        self._move_world(correction)
        positions = np.asarray(est.landmark_positions_world, dtype=float)
        landmarks = self.landmarks
        for row, lid in enumerate(est.landmark_ids.tolist()[: len(positions)]):
            if lid in landmarks:
                landmarks[lid] = positions[row]
        self.landmark_map.update_positions(est.landmark_ids, est.landmark_positions_world)

    def _adopt_scale(self, est: Estimate, fe_pose: np.ndarray) -> np.ndarray:
        """Before the back end's world is adopted: our pose of its keyframe in the scale of
        that world (stereo: already metric; the monocular front end rescales its map)."""
        return fe_pose

    def _move_world(self, correction: np.ndarray) -> None:
        """Move the local map and the poses by ``correction`` (new_from_old)."""
        # Batched, with the same products as one at a time (a stack of 3x3 @ 3 and of
        # 4x4 @ 4x4 matrix products: bit-identical results), in a fraction of the time: this
        # runs at the frame after each keyframe, the front end's slowest.
        if self.landmarks:
            points = np.array(list(self.landmarks.values()), dtype=float)
            moved = (correction[None, :3, :3] @ points[:, :, None])[:, :, 0] + correction[:3, 3]
            self.landmarks.update(zip(list(self.landmarks), moved, strict=True))
        if self.kf_poses:
            poses = correction[None] @ np.array(list(self.kf_poses.values()), dtype=float)
            self.kf_poses.update(zip(list(self.kf_poses), poses, strict=True))
        if self.world_from_body is not None:
            self.world_from_body = correction @ self.world_from_body
        if self.prev_world_from_body is not None:
            self.prev_world_from_body = correction @ self.prev_world_from_body
        self.last_known_pose = correction @ self.last_known_pose

    def _rigid_estimate(self, est: Estimate, fe_pose: np.ndarray) -> bool:
        if is_rigid(est.world_from_body, tol=1e-3) and np.isfinite(fe_pose).all():
            return True
        self.stats.state_log.append((est.t_ns, "back-end estimate ignored: not a rigid pose"))
        return False

    def finish(self) -> None:
        """End of the run, called once the back end has published its last estimate.

        The change of frame into the back end's world is applied by :meth:`process`, at the
        first frame after the first initialised estimate. A back end that falls behind (its
        worker starved of CPU) can publish that estimate only after our last frame: without
        this, the recorded trajectory stayed in the VO frame while the back end's keyframes
        were gravity aligned. The change of frame is then taken from the latest estimate, as
        the next frame would have. Nothing happens once the frame was changed: corrections
        after the last frame do not rewrite the (causal) online trajectory.
        """
        if self.reframed:
            return
        self._apply_estimate()
        est = self.latest_estimate
        if self.reframed and est is not None:
            self.stats.state_log.append(
                (est.t_ns, "back end's world adopted after the last frame (late initialisation)")
            )

    # ------------------------------------------------------------------ helpers
    def _undistorted_px(self, px: np.ndarray) -> np.ndarray:
        norm = self.cam0.undistort_points(px)
        return norm * [self.cam0.fx, self.cam0.fy] + [self.cam0.cx, self.cam0.cy]

    def _tracks_normalised(self) -> np.ndarray:
        """The tracks' pixels as they came into this frame (``self.px`` before its KLT),
        undistorted to normalised coordinates (N, 2): the predicted blur and the gyro's KLT
        guess both need them; computed once per frame."""
        if self._px_normalised is None:
            self._px_normalised = self.cam0.undistort_points(self.px)
        return self._px_normalised

    def _gyro_rotation(self, t0_ns: int, t1_ns: int) -> np.ndarray | None:
        """body(t0)_from_body(t1) from the gyro, or None without usable IMU."""
        if self.imu is None or not self.cfg.use_gyro_prediction:
            return None
        return integrate_gyro(self.imu.window(t0_ns, t1_ns), t0_ns, t1_ns, self.bias_gyro)

    def _result(self, frame: StereoFrame, state: str, t_start: float, **kw) -> TrackingResult:
        pose = kw.pop("world_from_body", None)
        rq_now = runqueue_wait_ns()
        runqueue_ms = (
            -1.0
            if rq_now is None or self._runqueue_start_ns is None
            else (rq_now - self._runqueue_start_ns) * 1e-6
        )
        return TrackingResult(
            t_ns=frame.t_ns,
            frame_index=frame.index,
            state=state,
            time_offset_ns=frame.time_offset_ns,
            segment_id=self.segment_id,
            world_from_body=None if pose is None else pose.copy(),
            is_keyframe=kw.pop("is_keyframe", False),
            keyframe_id=kw.pop("keyframe_id", -1),
            num_tracked=kw.pop("num_tracked", 0),
            num_inliers=kw.pop("num_inliers", 0),
            feature_pixels=self.px.copy(),
            feature_ages=self.ages.copy(),
            latency_ms=(time.perf_counter() - t_start) * 1e3,
            image_left=frame.left,
            reason=kw.pop("reason", ""),
            cpu_ms=(thread_cpu_s() - self._cpu_start_s) * 1e3,
            runqueue_ms=runqueue_ms,
            in_backend_world=self.reframed,
            anchor_keyframe_id=self._anchor_kf if pose is not None else -1,
            feature_reobserved=np.array(
                [i in self.reobserved_ids for i in self.ids.tolist()], dtype=bool
            ),
        )

    def _retire(self, lids: list[int]) -> None:
        """Landmarks no longer tracked go to the map (the back end keeps its own)."""
        if lids:
            self.landmark_map.retire(np.asarray(lids), np.array([self.landmarks[i] for i in lids]))
        for lid in lids:
            del self.landmarks[lid]
            self.reobserved_ids.discard(lid)

    def _count_landmarks(self, lids: np.ndarray) -> None:
        """Per-frame counts of tracked landmarks (PnP inliers), all and found again."""
        n = len(lids)
        old_ids = [i for i in lids.tolist() if i in self.reobserved_ids]
        old = len(old_ids)
        self._anchor_kf = (
            self.landmark_map.anchor_keyframe(np.asarray(old_ids))
            if old >= self.cfg.map_min_inliers
            else -1
        )
        self.stats.landmark_frames += 1
        self.stats.landmarks_tracked += n
        self.stats.landmarks_tracked_old += old
        if self._revisit:
            self.stats.revisit_frames += 1
            self.stats.revisit_landmarks += n
            self.stats.revisit_landmarks_old += old

    def _lose(self, frame: StereoFrame, t_start: float, reason: str) -> TrackingResult:
        if self.mapped:
            self.stats.tracking_losses += 1
            self.stats.state_log.append((frame.t_ns, f"lost: {reason}"))
        self.mapped = False
        self.stats.lost_frames += 1
        self.px = np.zeros((0, 2), np.float32)
        self.ids = np.zeros(0, np.int64)
        self.ages = np.zeros(0, np.int64)
        self._retire(list(self.landmarks))
        self._anchor_kf = -1
        self.templates.clear()
        self.world_from_body = None
        self.prev_world_from_body = None
        return self._result(frame, "lost", t_start, reason=reason)

    # ------------------------------------------------------------------ main entry
    def process(self, frame: StereoFrame) -> tuple[TrackingResult, Keyframe | None]:
        """Track one frame. Returns the tracking result and a keyframe when one was made
        (:meth:`track` then :meth:`after_pose`)."""
        result = self.track(frame)
        return result, self.after_pose()

    def track(self, frame: StereoFrame) -> TrackingResult:
        """Track one frame up to its pose: the result to publish at once. A keyframe this
        frame needs is made by :meth:`after_pose`, which the caller runs after publishing
        (the result already carries the keyframe's id)."""
        t_start = time.perf_counter()
        self._cpu_start_s = thread_cpu_s()
        self._runqueue_start_ns = runqueue_wait_ns()
        self.stats.frames += 1
        self._px_normalised = None
        self._apply_estimate()
        self.blur_px = self._predicted_blur(frame) if self.cfg.blur_pose_prior_min_px > 0 else 0.0
        image = frame.left
        mean_a, std_a = cv2.meanStdDev(image)
        mean, std = float(mean_a[0, 0]), float(std_a[0, 0])
        if mean < self.cfg.black_frame_max_mean or std < self.cfg.textureless_max_std:
            self.pyr_prev = None
            what = "black frame" if mean < self.cfg.black_frame_max_mean else "textureless frame"
            return self._lose(frame, t_start, what)
        pyr = build_pyramid(image, self.cfg)
        if not self.mapped or self.pyr_prev is None:
            result, self._keyframe_made = self._start_segment(frame, pyr, t_start)
        else:
            result = self._track(frame, pyr, t_start)
        self.pyr_prev = pyr
        self.t_prev_ns = frame.t_ns
        return result

    def after_pose(self) -> Keyframe | None:
        """The frame's work that its pose does not wait for: the keyframe :meth:`track`
        decided on (detection, stereo matching, new landmarks) and the new landmarks'
        affine templates. A robot gets the pose that much sooner (ORB-SLAM's tracking
        likewise hands keyframe insertion on); the next frame still waits for it."""
        t0 = time.perf_counter()
        kf, self._keyframe_made = self._keyframe_made, None
        if self._keyframe_due is not None:
            frame, pyr = self._keyframe_due
            self._keyframe_due = None
            kf = self._make_keyframe(frame, pyr)
        self.templates.build_pending()
        self.stats.after_pose_ms.append((time.perf_counter() - t0) * 1e3)
        return kf

    def _imu_prior(self, t_ns: int) -> np.ndarray | None:
        """world_from_body at t_ns dead-reckoned with the IMU from the latest back-end estimate."""
        est = self.latest_estimate
        if est is None or self.imu is None or t_ns - est.t_ns > 3_000_000_000:
            return None
        # Propagate incrementally from the last propagated state while the estimate is the
        # same one: O(samples since the last frame), not O(samples since the estimate).
        cached = self._prior_cache
        if cached is not None and cached[0] is est and cached[1] <= t_ns:
            t0, pose0, vel0 = cached[1], cached[2], cached[3]
        else:
            t0, pose0, vel0 = est.t_ns, est.world_from_body, est.velocity_world_m_s
        out = propagate_pose(
            self.imu.window(t0, t_ns),
            t0,
            t_ns,
            pose0,
            vel0,
            est.bias_gyro_rad_s,
            est.bias_accel_m_s2,
            self.gravity_m_s2,
        )
        if out is None:
            return None
        self._prior_cache = (est, t_ns, out[0], out[1])
        return out[0]

    def _predict_pose(self, t_ns: int, rot_b0_b1: np.ndarray | None) -> np.ndarray:
        assert self.world_from_body is not None
        prior = self._imu_prior(t_ns)
        if prior is not None:
            return prior
        pose = self.world_from_body.copy()
        if self.prev_world_from_body is not None and self.prev_dt_ns > 0:
            # constant velocity over the frame interval
            delta = invert_transform(self.prev_world_from_body) @ self.world_from_body
            ratio = (t_ns - self.t_prev_ns) / self.prev_dt_ns
            if 0.0 < ratio < 5.0:
                # cv2.Rodrigues: scipy's Rotation cost ~0.7 ms per frame here
                rotvec, _ = cv2.Rodrigues(np.ascontiguousarray(delta[:3, :3]))
                rot, _ = cv2.Rodrigues(rotvec * ratio)
                delta = make_transform(rot, delta[:3, 3] * ratio)
                pose = self.world_from_body @ delta
        if rot_b0_b1 is not None:
            pose[:3, :3] = self.world_from_body[:3, :3] @ rot_b0_b1
        return pose

    def _track(self, frame: StereoFrame, pyr: np.ndarray, t_start: float) -> TrackingResult:
        assert self.pyr_prev is not None and self.world_from_body is not None
        rot_b0_b1 = self._gyro_rotation(self.t_prev_ns, frame.t_ns)
        guess = None
        if rot_b0_b1 is not None and len(self.px):
            rot_c1_c0 = (self.cam0_from_body[:3, :3] @ rot_b0_b1 @ self.body_from_cam0[:3, :3]).T
            rays = np.hstack([self._tracks_normalised(), np.ones((len(self.px), 1))])
            rays1 = rays @ rot_c1_c0.T
            if (rays1[:, 2] > 0.1).all():
                guess = self.cam0.project(rays1)
        pyr_from, pyr_to = self.pyr_prev, pyr
        if self.cfg.klt_match_brightness:
            ratio = brightness_ratio(
                self.pyr_prev, pyr, self.px, self.px if guess is None else guess, self.reduced
            )
            pyr_from, pyr_to = match_brightness(self.pyr_prev, pyr, ratio)
        pose_guess = self._predict_pose(frame.t_ns, rot_b0_b1)
        has_lm = np.array([i in self.landmarks for i in self.ids.tolist()], dtype=bool)
        px, ok = self._track_points(pyr_from, pyr_to, guess, pose_guess, has_lm)
        num_tracked = int(ok.sum())
        self.px, self.ids, self.ages = px[ok], self.ids[ok], self.ages[ok] + 1
        has_lm = has_lm[ok]
        if self.cfg.affine_refinement:
            period = self.cfg.affine_period_frames
            turn = (self.ids >= 0) & (self.ids % period == self.stats.frames % period)
            px_fit, has_template, refitted = self.templates.refine(
                self.ids[turn], self.px[turn], pyr
            )
            self.px[turn] = px_fit
            self.stats.track_refits += int(has_template.sum())
            self.stats.track_refits_kept += int(refitted.sum())
        if has_lm.sum() < self.cfg.min_pnp_inliers:
            return self._lose(frame, t_start, f"only {int(has_lm.sum())} landmarks tracked")
        idx = np.flatnonzero(has_lm)
        obj = np.array([self.landmarks[i] for i in self.ids[idx].tolist()])
        img = self._undistorted_px(self.px[idx])
        ok_pnp, inl, rvec, tvec = self._pnp_ransac(obj, img, pose_guess)
        n_in = len(inl)
        if not ok_pnp or n_in < self.cfg.min_pnp_inliers:
            return self._lose(frame, t_start, f"PnP found {n_in} inliers")
        pose = self._refined_pose(obj[inl], img[inl], rvec, tvec)
        if 0 < self.cfg.blur_pose_prior_min_px < self.blur_px:
            pose = self._blurred_pose(pose, obj[inl], img[inl], frame.t_ns)
        self._count_landmarks(self.ids[idx[inl]])
        # drop PnP outliers from the tracks
        keep = np.ones(len(self.ids), dtype=bool)
        outliers = np.setdiff1d(np.arange(len(idx)), inl)
        keep[idx[outliers]] = False
        self.px, self.ids, self.ages = self.px[keep], self.ids[keep], self.ages[keep]
        self.prev_world_from_body = self.world_from_body
        self.prev_dt_ns = frame.t_ns - self.t_prev_ns
        self.world_from_body = pose
        self.last_known_pose = pose
        self.stats.tracked += 1
        # forget landmarks that are no longer tracked (the back end keeps its own)
        tracked = set(self.ids.tolist())
        self._retire([lid for lid in self.landmarks if lid not in tracked])
        keyframe = self._need_keyframe(frame.t_ns, n_in)
        if keyframe:
            self._keyframe_due = (frame, pyr)  # made by after_pose, with the next id
        return self._result(
            frame,
            "tracking",
            t_start,
            world_from_body=pose,
            is_keyframe=keyframe,
            keyframe_id=self.next_keyframe_id if keyframe else -1,
            num_tracked=num_tracked,
            num_inliers=n_in,
        )

    def _track_points(
        self,
        pyr_from: np.ndarray,
        pyr_to: np.ndarray,
        gyro_guess: np.ndarray | None,
        world_from_body_guess: np.ndarray,
        has_landmark: np.ndarray,
    ) -> tuple[np.ndarray, np.ndarray]:
        """KLT of the tracks ``self.px`` into the new image: ``(pixels (N, 2), ok (N,))``;
        ``has_landmark`` (N,): which tracks are of landmarks.

        A landmark's track starts at the landmark's projection from the predicted pose
        (``world_from_body_guess``: IMU dead reckoning from the back end's estimate, else
        constant velocity with the gyro's rotation), the others at the gyro-rotated pixel
        (``gyro_guess``), all on ``klt_predicted_levels`` pyramid levels instead of
        ``klt_pyramid_levels``: with the back end's estimate the projection is within a few
        pixels of where KLT ends. When more than ``klt_predicted_max_lost`` of the landmark
        tracks are lost so (a bad prediction: constant velocity through a sharp turn), the
        lost tracks are tracked again from the gyro guess over the full pyramid.
        """
        cfg = self.cfg
        n = len(self.px)
        levels = cfg.klt_predicted_levels
        if levels >= cfg.klt_pyramid_levels or n == 0:
            return track_klt(pyr_from, pyr_to, self.px, cfg, guess_to=gyro_guess)
        rows = has_landmark
        start = (self.px if gyro_guess is None else gyro_guess).astype(np.float32)
        predicted = np.zeros(n, bool)
        if rows.any():
            cam_from_world = self.cam0_from_body @ invert_transform(world_from_body_guess)
            pts = np.array([self.landmarks[i] for i in self.ids[rows].tolist()])
            pts_cam = transform_points(cam_from_world, pts)
            front = pts_cam[:, 2] > 0.1
            idx = np.flatnonzero(rows)[front]
            proj = self.cam0.project(pts_cam[front])
            h, w = pyr_to.shape[:2]
            inside = (proj >= 0).all(axis=1) & (proj[:, 0] <= w - 1) & (proj[:, 1] <= h - 1)
            start[idx[inside]] = proj[inside]
            predicted[idx[inside]] = True
        px, ok = track_klt(pyr_from, pyr_to, self.px, cfg, guess_to=start, levels=levels)
        lost = predicted & ~ok
        self.stats.klt_predicted += int(predicted.sum())
        if lost.sum() > cfg.klt_predicted_max_lost * max(int(predicted.sum()), 1):
            again = ~ok
            self.stats.klt_retracked += int(again.sum())
            px[again], ok[again] = track_klt(
                pyr_from,
                pyr_to,
                self.px[again],
                cfg,
                guess_to=None if gyro_guess is None else gyro_guess[again],
            )
        return px, ok

    def _pnp_ransac(
        self, obj: np.ndarray, img: np.ndarray, guess_world_from_body: np.ndarray
    ) -> tuple[bool, np.ndarray, np.ndarray, np.ndarray]:
        """PnP RANSAC of world points ``obj`` seen at undistorted pixels ``img`` from the
        guess: (ok, inlier rows, rvec, tvec of cam0_from_world)."""
        cam_from_world = self.cam0_from_body @ invert_transform(guess_world_from_body)
        rvec, _ = cv2.Rodrigues(cam_from_world[:3, :3])
        tvec = cam_from_world[:3, 3].reshape(3, 1).copy()
        ok, rvec, tvec, inliers = cv2.solvePnPRansac(
            obj,
            img,
            self.K,
            None,
            rvec,
            tvec,
            useExtrinsicGuess=True,
            iterationsCount=100,
            reprojectionError=self.cfg.pnp_reprojection_px,
            confidence=0.999,
            flags=cv2.SOLVEPNP_ITERATIVE,
        )
        inl = np.zeros(0, np.int64) if inliers is None else inliers.ravel()
        return bool(ok), inl, rvec, tvec

    def _blurred_pose(
        self, world_from_body: np.ndarray, obj: np.ndarray, img: np.ndarray, t_ns: int
    ) -> np.ndarray:
        """A blurred frame's PnP pose fused with the IMU's prediction (``blur_pose_prior_min_px``):
        the information-weighted mean of the two in the PnP pose's tangent space, a body-frame
        rotation ``phi`` and translation ``rho`` (``world_from_body @ [exp(phi) | rho]``), so the
        result does not depend on where the world's origin is. The PnP's information is
        ``J^T J / sigma^2`` over its inliers (world points ``obj``, undistorted pixels ``img``),
        ``sigma`` the pixel sigma grown by the blur (``blur_pose_sigma_fraction``); the
        prediction's is diagonal from its rotation and position sigmas."""
        cfg = self.cfg
        predicted = self._imu_prior(t_ns)
        if predicted is None:
            return world_from_body
        self.stats.blur_pose_fused += 1
        body_from_world = invert_transform(world_from_body)
        p_body = transform_points(body_from_world, obj)
        p_cam = transform_points(self.cam0_from_body, p_body)
        x, y, z = p_cam.T
        d_px_d_cam = np.zeros((len(z), 2, 3))  # pinhole: the pixels are undistorted
        d_px_d_cam[:, 0, 0] = self.cam0.fx / z
        d_px_d_cam[:, 0, 2] = -self.cam0.fx * x / z**2
        d_px_d_cam[:, 1, 1] = self.cam0.fy / z
        d_px_d_cam[:, 1, 2] = -self.cam0.fy * y / z**2
        # the point in the perturbed body: exp(-phi) (p - rho) ~ p + [p]x phi - rho
        skew_p = skew_batch(p_body)
        cam_from_body_rot = self.cam0_from_body[:3, :3]
        d_cam_d_xi = np.concatenate(
            [cam_from_body_rot @ skew_p, np.broadcast_to(-cam_from_body_rot, skew_p.shape)],
            axis=2,
        )
        jac = (d_px_d_cam @ d_cam_d_xi).reshape(-1, 6)
        sigma_px = np.hypot(
            cfg.blur_pose_pixel_sigma_px, cfg.blur_pose_sigma_fraction * self.blur_px
        )
        info_pnp = jac.T @ jac / sigma_px**2
        body_from_predicted = body_from_world @ predicted
        xi_predicted = np.r_[so3_log(body_from_predicted[:3, :3]), body_from_predicted[:3, 3]]
        info_predicted = np.diag(
            [cfg.blur_pose_prior_sigma_rad**-2] * 3 + [cfg.blur_pose_prior_sigma_m**-2] * 3
        )
        xi = np.linalg.solve(info_pnp + info_predicted, info_predicted @ xi_predicted)
        return world_from_body @ make_transform(so3_exp(xi[:3]), xi[3:])

    def _predicted_blur(self, frame: StereoFrame) -> float:
        """The frame's motion blur from the gyro and its exposure (``motion_blur``): the
        median streak of the tracks (at their last pixels), px; 0 without exposure or IMU.
        Where a bound of it from the gyro's turn alone (``motion_blur.BlurBound``) is at most
        ``blur_pose_prior_min_px``, the bound: the blur itself is not needed then (half the
        cost of the prediction, most frames of a slow sequence)."""
        if frame.exposure_ns <= 0 or self.imu is None:
            return 0.0
        turn = rate_turn(self.imu, frame.t_ns, frame.exposure_ns, self.bias_gyro)
        if turn is None:
            return 0.0
        body0_from_body1, span_s = turn
        exposure_s = frame.exposure_ns * 1e-9
        turn_rad = rotation_angle_rad(body0_from_body1) / span_s * exposure_s
        bounds = self._blur_bound
        min_px = self.cfg.blur_pose_prior_min_px
        if len(self.px) and bounds is not None and bounds.lowest_px(turn_rad) <= min_px:
            bound = bounds.length_px(self._tracks_normalised(), turn_rad)
            if bound <= min_px:
                return bound
        rate = np.asarray(so3_log(body0_from_body1), dtype=float) / span_s
        return blur_length_px(
            rate,
            exposure_s,
            self.cam0_from_body[:3, :3],
            self.cam0,
            self.px,
            self._tracks_normalised(),
        )

    def _refined_pose(
        self, obj: np.ndarray, img: np.ndarray, rvec: np.ndarray, tvec: np.ndarray
    ) -> np.ndarray:
        """world_from_body from a PnP solution refined (LM) on its inliers ``obj``/``img``."""
        rvec, tvec = cv2.solvePnPRefineLM(obj, img, self.K, None, rvec, tvec)
        rot, _ = cv2.Rodrigues(rvec)
        return invert_transform(make_transform(rot, tvec.ravel())) @ self.cam0_from_body

    def _need_keyframe(self, t_ns: int, num_inliers: int) -> bool:
        cfg = self.cfg
        since_s = (t_ns - self.kf_t_ns) * 1e-9
        if since_s >= cfg.keyframe_max_interval_s:
            return True
        ids = self.ids.tolist()
        in_kf = [i in self.kf_px for i in ids]
        still = [self.kf_px[i] for i, seen in zip(ids, in_kf, strict=True) if seen]
        ratio = len(still) / max(self.kf_num_landmarks, 1)
        if since_s < cfg.keyframe_min_interval_s and ratio >= 0.5:
            return False  # fast motion must not make every frame a keyframe
        if ratio < cfg.keyframe_min_tracked_ratio:
            return True
        if num_inliers < 3 * cfg.min_pnp_inliers:
            return True
        if still:
            parallax = float(np.median(np.linalg.norm(self.px[in_kf] - np.array(still), axis=1)))
            if parallax > cfg.keyframe_min_parallax_px:
                return True
        return False

    def _start_segment(
        self, frame: StereoFrame, pyr: np.ndarray, t_start: float
    ) -> tuple[TrackingResult, Keyframe | None]:
        if frame.right is None:
            return self._lose(frame, t_start, "no right image to start from stereo"), None
        self.px = np.zeros((0, 2), np.float32)
        self.ids = np.zeros(0, np.int64)
        self.ages = np.zeros(0, np.int64)
        self._retire(list(self.landmarks))
        self._anchor_kf = -1
        self.templates.clear()
        pose = self.last_known_pose.copy()
        prior = self._imu_prior(frame.t_ns) if self.stats.segments else None
        reloc = None
        if self.stats.segments and self.relocaliser is not None:
            # Against the existing map first: found there, the segment simply continues.
            recent = sorted(self.kf_poses)[-6:]
            reloc = self.relocaliser.relocalise(
                frame.left, frame.t_ns, segment_id=self.segment_id, recent_ids=recent
            )
        if reloc is not None and prior is not None:
            # A relocalisation that contradicts IMU dead reckoning over a short gap is an alias.
            delta = invert_transform(prior) @ np.asarray(reloc.world_from_body, dtype=float)
            angle = rotation_angle_rad(delta[:3, :3])
            if np.linalg.norm(delta[:3, 3]) > 1.0 or angle > np.radians(20.0):
                self.stats.state_log.append(
                    (frame.t_ns, "relocalisation rejected: it contradicts the IMU prior")
                )
                reloc = None
        if reloc is not None:
            pose = np.asarray(reloc.world_from_body, dtype=float).copy()
        elif prior is not None:
            pose = prior  # dead-reckoned across the gap: the new segment starts where we are
        elif self.t_prev_ns and self.stats.segments:
            rot = self._gyro_rotation(self.t_prev_ns, frame.t_ns)
            if rot is not None:
                pose[:3, :3] = pose[:3, :3] @ rot
        self.world_from_body = pose
        self.prev_world_from_body = None
        # Relocalised, or bridged by IMU dead reckoning from the back end's estimate: the map's
        # frame carries on, so does the segment. Only without either does a new segment start.
        continues = reloc is not None or (prior is not None and self.stats.segments > 0)
        kf = self._make_keyframe(frame, pyr, new_segment=not continues)
        if kf is None:
            self.world_from_body = None
            return self._lose(frame, t_start, "too few stereo matches to start a map"), None
        self.stats.tracked += 1
        self.last_known_pose = pose
        state, reason = "init", ""
        if reloc is not None:
            self.mapped = True
            self.stats.relocalisations += 1
            state = "relocalised"
            reason = f"against keyframe {reloc.keyframe_id} ({reloc.inliers} inliers)"
            self.stats.state_log.append((frame.t_ns, f"relocalised {reason}"))
        elif continues:
            self.mapped = True
            self.stats.imu_bridged += 1
            state = "recovered"
            reason = "IMU dead reckoning across the gap"
            self.stats.state_log.append((frame.t_ns, f"recovered: {reason}"))
        return (
            self._result(
                frame,
                state,
                t_start,
                world_from_body=pose,
                is_keyframe=True,
                keyframe_id=kf.keyframe_id,
                num_inliers=len(kf.landmark_ids),
                reason=reason,
            ),
            kf,
        )

    def _reuse_map(self, frame: StereoFrame) -> None:
        """Find untracked landmarks of the map in this keyframe's image and track them again.

        The matches must agree on one pose (PnP RANSAC from the tracked pose); that pose may
        differ from the tracked one by the drift since the landmarks were last seen, within
        ``map_max_correction_m`` / ``_deg``. The local map then moves onto the old landmarks
        (a :class:`FrontendCorrection`, as when the back end re-anchors it): from this frame
        on the pose is tracked against both, in the old landmarks' frame.
        """
        assert self.world_from_body is not None
        cfg = self.cfg
        params = SearchParams(
            radius_px=cfg.map_search_radius_px,
            min_ncc=cfg.map_min_ncc,
            unique_exclusion_px=cfg.map_unique_exclusion_px,
            max_candidates=cfg.map_max_candidates,
            max_view_angle_deg=cfg.map_max_view_angle_deg,
            max_scale_change=cfg.map_max_scale_change,
            half_window_px=cfg.affine_half_window_px,
            max_rms=cfg.map_max_patch_rms,
        )
        world_from_cam = self.world_from_body @ self.body_from_cam0
        found = self.landmark_map.search(
            frame.left, world_from_cam, self.cam0, self.segment_id, params
        )
        self.stats.map_searches += 1
        self.stats.map_candidates += found.candidates
        self.stats.map_found += len(found.ids)
        self._revisit = found.candidates >= cfg.map_min_inliers
        if len(found.ids) < cfg.map_min_inliers:
            return
        # checked together with the tracked landmarks: one pose must fit both (the tracked
        # ones alone fix it well; a few old landmarks alone can trade rotation for translation)
        has_lm = np.array([i in self.landmarks for i in self.ids.tolist()], dtype=bool)
        tracked_obj = np.array([self.landmarks[i] for i in self.ids[has_lm].tolist()]).reshape(
            -1, 3
        )
        obj = np.vstack([tracked_obj, found.positions_world])
        img = np.vstack(
            [
                self._undistorted_px(self.px[has_lm]).reshape(-1, 2),
                self._undistorted_px(found.pixels),
            ]
        )
        ok, inl, rvec, tvec = self._pnp_ransac(obj, img, self.world_from_body)
        n_tracked = len(tracked_obj)
        old_inl = inl[inl >= n_tracked] - n_tracked
        if not ok or len(old_inl) < cfg.map_min_inliers:
            # drifted by more than the inlier threshold: the old landmarks alone, if they are
            # many enough to fix the pose well by themselves
            obj, img = obj[n_tracked:], img[n_tracked:]
            ok, inl, rvec, tvec = self._pnp_ransac(obj, img, self.world_from_body)
            old_inl = inl
            if not ok or len(inl) < cfg.map_min_inliers_alone:
                self.stats.map_rejected += 1
                return
        pose = self._refined_pose(obj[inl], img[inl], rvec, tvec)
        correction = nearest_rigid(pose @ invert_transform(self.world_from_body))
        moved_m = float(np.linalg.norm(correction[:3, 3]))
        if (
            moved_m > cfg.map_max_correction_m
            or np.degrees(rotation_angle_rad(correction[:3, :3])) > cfg.map_max_correction_deg
        ):
            self.stats.map_rejected += 1
            self.stats.state_log.append(
                (frame.t_ns, f"map landmarks found again but {moved_m:.2f} m away: ignored")
            )
            return
        inl = old_inl
        self.stats.map_corrections += 1
        self.stats.map_correction_max_m = max(self.stats.map_correction_max_m, moved_m)
        self.corrections.append(FrontendCorrection(frame.t_ns, correction, False))
        self._move_world(correction)
        self._track_again(found.take(inl))

    def _track_again(self, found: MapMatches) -> None:
        """Add the landmarks found again to the tracks; a track of a newer landmark on the
        same spot (the same point, found twice) gives way to the older one."""
        near = np.zeros(len(self.px), bool)
        if len(self.px):
            d = np.linalg.norm(
                self.px[:, None, :] - found.pixels[None, :, :].astype(np.float32), axis=2
            )
            near = d.min(axis=1) < 2.0
        if near.any():
            self._retire([int(i) for i in self.ids[near].tolist() if i in self.landmarks])
            keep = ~near
            self.px, self.ids, self.ages = self.px[keep], self.ids[keep], self.ages[keep]
        self.px = np.vstack([self.px, found.pixels.astype(np.float32)])
        self.ids = np.concatenate([self.ids, found.ids])
        self.ages = np.concatenate([self.ages, np.zeros(len(found.ids), np.int64)])
        for lid, pos in zip(found.ids.tolist(), found.positions_world, strict=True):
            self.landmarks[lid] = np.asarray(pos, float)
        self.reobserved_ids.update(found.ids.tolist())
        self.landmark_map.mark_tracked(found.ids)
        if self.cfg.affine_refinement:
            self.templates.restore(found.ids, found.templates, found.linear)
        self.stats.map_reobserved += len(found.ids)

    def _make_keyframe(
        self, frame: StereoFrame, pyr: np.ndarray, new_segment: bool = False
    ) -> Keyframe | None:
        assert self.world_from_body is not None
        self._revisit = False
        in_final_world = self.reframed or not self.has_backend
        if self.cfg.map_reuse and self.mapped and not new_segment and in_final_world:
            self._reuse_map(frame)
        new_px = detect_features(frame.left, self.px, self.cfg)
        px = np.vstack([self.px, new_px]).astype(np.float32)
        ids = np.concatenate([self.ids, np.full(len(new_px), -1, np.int64)])
        ages = np.concatenate([self.ages, np.zeros(len(new_px), np.int64)])
        right_px = np.full((len(px), 2), np.nan)
        if frame.right is not None and len(px):
            assert self.stereo is not None
            pyr_right = build_pyramid(frame.right, self.cfg)
            world_from_cam = self.world_from_body @ self.body_from_cam0
            known_world = np.full((len(px), 3), np.nan)
            for row, lid in enumerate(ids.tolist()):
                if lid >= 0 and lid in self.landmarks:
                    known_world[row] = self.landmarks[lid]
            known_cam = transform_points(invert_transform(world_from_cam), known_world)
            matches = self.stereo.match(pyr, pyr_right, px, known_cam, self.reduced)
            right_px[matches.ok] = matches.pixels_right[matches.ok]
            need = matches.ok & (ids < 0)
            pts_world = (
                matches.points_cam0_m[need] @ world_from_cam[:3, :3].T + world_from_cam[:3, 3]
            )
            new_ids = np.arange(self.next_landmark_id, self.next_landmark_id + int(need.sum()))
            self.next_landmark_id += len(new_ids)
            ids[need] = new_ids
            for lid, p in zip(new_ids.tolist(), pts_world, strict=True):
                self.landmarks[lid] = p
            self.landmark_map.add(
                new_ids,
                pts_world,
                px[need],
                frame.left,
                world_from_cam,
                self.cam0,
                self.segment_id + 1 if new_segment else self.segment_id,
                self.next_keyframe_id,
                refined=not self.has_backend,
            )
            if self.cfg.affine_refinement:
                self.templates.keep_only(ids[(ids >= 0) & ~need])
                self.templates.add(new_ids, px[need], frame.left)
        has_lm = ids >= 0
        if new_segment and has_lm.sum() < max(2 * self.cfg.min_pnp_inliers, 30):
            return None
        # features that never got a landmark are dropped at the next keyframe if still without
        self.px, self.ids, self.ages = px, ids, ages
        if new_segment:
            self.segment_id += 1
            self.stats.segments += 1
            self.mapped = True
            self.stats.state_log.append((frame.t_ns, f"map segment {self.segment_id} started"))
        kf_id = self.next_keyframe_id
        self.next_keyframe_id += 1
        self.stats.keyframes += 1
        self.kf_t_ns = frame.t_ns
        self.kf_px = {int(i): p for i, p in zip(ids[has_lm], px[has_lm], strict=True)}
        self.kf_num_landmarks = int(has_lm.sum())
        prev_pose = self.kf_poses.get(kf_id - 1)  # moved by the corrections since
        self.kf_poses[kf_id] = self.world_from_body.copy()
        if len(self.kf_poses) > MAX_STORED_KEYFRAME_POSES:
            del self.kf_poses[min(self.kf_poses)]
        lm_ids = ids[has_lm]
        und_left = self._undistorted_px(px[has_lm]) if has_lm.any() else np.zeros((0, 2))
        r = right_px[has_lm]
        und_right = np.full_like(r, np.nan)
        okr = np.isfinite(r).all(axis=1)
        if okr.any():
            cam1 = self.calib.cameras[1].intrinsics
            und_right[okr] = cam1.undistort_points(r[okr]) * [cam1.fx, cam1.fy] + [cam1.cx, cam1.cy]
        return Keyframe(
            t_ns=frame.t_ns,
            keyframe_id=kf_id,
            frame_index=frame.index,
            segment_id=self.segment_id,
            world_from_body_vo=self.world_from_body.copy(),
            landmark_ids=lm_ids.copy(),
            pixels_left_undist=und_left,
            pixels_right_undist=und_right,
            points_world_vo=np.array([self.landmarks[i] for i in lm_ids.tolist()]).reshape(-1, 3),
            image_left=frame.left,
            image_right=frame.right,
            time_offset_ns=frame.time_offset_ns,
            previous_keyframe_id=kf_id - 1 if prev_pose is not None else -1,
            previous_keyframe_world_from_body=None if prev_pose is None else prev_pose.copy(),
        )

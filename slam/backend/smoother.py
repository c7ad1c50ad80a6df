"""The visual-inertial estimator: an iSAM2 fixed-lag smoother over keyframe states.

``VioBackend`` is a plain synchronous object (no threads): the pipeline stage feeds it
``add_imu(sample)`` and ``add_keyframe(kf)``, and reads ``estimate()``. Per keyframe k it adds
state ``X(k)`` (world_from_body, gtsam Pose3), ``V(k)`` (world velocity), ``B(k)`` (IMU biases),
a ``CombinedImuFactor`` to the previous state (or, across an IMU gap, a weak VO relative-pose
factor plus velocity/bias random walks), and Huber-robust ``GenericProjectionFactorCal3_S2``
factors for the left and right camera (``body_P_sensor = body_from_cam``: EuRoC is not
rectified, so no stereo factor) on landmarks ``L(id)``. A landmark enters once
``min_keyframes_per_landmark`` keyframes in the window saw it and it triangulates with small
reprojection error; later observations are gated by their predicted reprojection error; after
each update landmarks whose newest observation is an outlier are culled (that observation is
removed, no more are added). Old states and landmarks are marginalised
(``slam.backend.fixed_lag``, ``lag_s``), so memory and cost stay bounded.

Before initialisation the back end buffers keyframes and publishes uninitialised estimates in
the front end's VO frame; after initialisation (``slam.backend.init``) everything is in a
gravity-aligned world (z up), ``world = world_from_vo @ vo``.

Failure handling: an exception from GTSAM (e.g. an indeterminate system) or a divergence
(non-finite values, velocity or position jump from the IMU prediction, bias out of range)
resets the smoother from the last good state (pose, velocity and bias priors), counts it and
retries the keyframe; a second failure adds the keyframe without visual factors.
"""

from __future__ import annotations

import dataclasses
import logging
import time
from dataclasses import dataclass, field
from typing import Any, cast

import gtsam
import numpy as np

from slam.backend.config import BackendConfig
from slam.backend.fixed_lag import FixedLagSmoother
from slam.backend.imu import (
    backend_imu_buffer,
    bias_noise,
    integration_pieces,
    make_bias,
    pose_noise,
    preintegrate,
    preintegration_params,
)
from slam.backend.imu_intrinsics import KeyframeState, OnlineImuIntrinsics
from slam.backend.init import (
    MovingInitResult,
    is_still,
    moving_init,
    still_init_align,
    still_init_kalman,
    world_from_vo_gravity,
)
from slam.backend.mono_init import (
    ScaleCheck,
    align_mono,
    batch_start,
    check_scale,
    check_scale_by_imu_fit,
    refine_vo_poses,
    scale_check_streak,
    start_gate,
)
from slam.backend.time_offset import OnlineTimeOffset
from slam.core.calibration import Calibration
from slam.core.errors import SlamError
from slam.core.geometry import invert_transform, scale_body_pose
from slam.core.messages import Estimate, ImuSample, Keyframe, KeyframeInertial

log = logging.getLogger(__name__)


def X(k: int) -> int:  # noqa: N802 - GTSAM's naming of state keys
    return gtsam.symbol("x", k)


def V(k: int) -> int:  # noqa: N802
    return gtsam.symbol("v", k)


def B(k: int) -> int:  # noqa: N802
    return gtsam.symbol("b", k)


def L(landmark_id: int) -> int:  # noqa: N802
    return gtsam.symbol("l", int(landmark_id))


class EstimatorFailure(RuntimeError):
    """A divergence detected after an update (triggers a reset)."""


@dataclass
class _State:
    """A keyframe state in the window."""

    k: int
    keyframe_id: int
    t_ns: int
    world_from_body_vo: np.ndarray | None
    # the raw IMU pieces from the previous state (the IMU intrinsics' fit, the published
    # ``KeyframeInertial``; None: not kept)
    raw_pieces: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None
    previous_keyframe_id: int = -1  # the state before it, joined by ``raw_pieces``


@dataclass
class _Obs:
    k: int
    uv_left: np.ndarray
    uv_right: np.ndarray | None


@dataclass
class _GoodState:
    """The newest state that passed the divergence checks (the reset point)."""

    k: int
    keyframe_id: int
    t_ns: int
    pose: gtsam.Pose3
    velocity: np.ndarray
    bias: gtsam.imuBias.ConstantBias
    world_from_body_vo: np.ndarray | None
    keyframe: Keyframe | None = None  # its observations seed the tracks after a reset


@dataclass
class BackendStats:
    """Counters and timings; read them for logs, bench tables and tests."""

    keyframes: int = 0
    resets: int = 0
    init_method: str = ""
    init_t_ns: int = -1
    observations_added: int = 0
    observations_gated: int = 0
    observations_removed: int = 0
    landmarks_inserted: int = 0
    landmarks_culled: int = 0
    map_landmarks_inserted: int = 0
    """Landmarks seen again after they left the window: back as variables held by a prior at
    their last estimated position (map reuse)..."""
    map_observations: int = 0
    """...and their observations."""
    keyframes_without_visual: int = 0
    init_state: str = ""
    """Monocular: "initialising" (alignments tried and failed so far) or "initialised"."""
    vo_scale: float = 1.0
    """Monocular: metres per VO unit of the accepted alignment."""
    mono_init_attempts: list[dict[str, Any]] = field(default_factory=list)
    """Monocular: every alignment tried (time, keyframes, scale, its check, why rejected): the
    scale estimate's history until one is accepted."""
    mono_scale_checks: list[dict[str, Any]] = field(default_factory=list)
    """Monocular: the scale checks after the start (``mono_scale_check_window_s``): time,
    scale, its standard deviation, whether counted, whether the smoother was corrected."""
    mono_scale_corrections: int = 0
    mono_reinits: int = 0
    """Monocular, ``mono_reinit_residual_m``: times the start was redone after a scale check's
    IMU-fit residual said the smoother slipped."""
    mono_init_batch_scale_change: float = 0.0
    """Monocular, ``mono_init_batch``: the start's batch adjustment moved the alignment's scale
    by this factor (0: no batch ran; 1 +- its failure: the alignment's start was used)."""
    mono_init_batch_velocity_sigma_m_s: float = 0.0
    """...and the newest velocity's standard deviation (largest axis) it handed on."""
    keyframes_held_for_time_offset: int = 0
    update_times_s: list[float] = field(default_factory=list)  # wall time per add_keyframe
    update_cpu_s: list[float] = field(default_factory=list)  # this thread's CPU time per call
    factor_counts: list[int] = field(default_factory=list)
    failures: list[str] = field(default_factory=list)


class VioBackend:
    """Stereo-inertial fixed-lag smoother with initialisation and failure recovery."""

    def __init__(
        self,
        calibration: Calibration,
        config: BackendConfig | None = None,
        publish_inertial: bool = False,
    ) -> None:
        """``publish_inertial``: keep every keyframe state's raw IMU readings from the one
        before it and hand each state, once final, to :meth:`take_inertial` (the loop
        closer's IMU factors, ``loop.global_ba_imu``)."""
        if calibration.imu is None:
            raise SlamError("the visual-inertial back end needs an IMU calibration; use stereo-vo")
        self.calibration = calibration
        self.config = config or BackendConfig()
        self.imu_calibration = calibration.imu
        self.imu = backend_imu_buffer(calibration.imu, self.config)
        self.stats = BackendStats()
        self._params = preintegration_params(calibration.imu)
        cams = calibration.cameras[:2]
        self._cal = [
            gtsam.Cal3_S2(c.intrinsics.fx, c.intrinsics.fy, 0.0, c.intrinsics.cx, c.intrinsics.cy)
            for c in cams
        ]
        self._k_mats = [c.intrinsics.K for c in cams]
        self._body_from_cam = [np.asarray(c.body_from_cam, dtype=float) for c in cams]
        self._body_p_cam = [gtsam.Pose3(m) for m in self._body_from_cam]
        self._pixel_noise = gtsam.noiseModel.Robust.Create(
            gtsam.noiseModel.mEstimator.Huber.Create(self.config.huber_k),
            gtsam.noiseModel.Isotropic.Sigma(2, self.config.pixel_sigma_px),
        )
        if self.config.landmark_model not in ("projection", "smart"):
            raise SlamError(
                f"unknown landmark_model {self.config.landmark_model!r}; use projection or smart"
            )
        self._smart_params = gtsam.SmartProjectionParams()
        self._smart_params.setLinearizationMode(gtsam.LinearizationMode.HESSIAN)
        self._smart_params.setDegeneracyMode(gtsam.DegeneracyMode.ZERO_ON_DEGENERACY)
        self._smart_params.setDynamicOutlierRejectionThreshold(self.config.outlier_reprojection_px)
        self._smart_params.setLandmarkDistanceThreshold(self.config.max_depth_m)
        self._rig = gtsam.CameraSetPinholePoseCal3_S2()
        for pose_bc, cal in zip(self._body_p_cam, self._cal):
            self._rig.push_back(gtsam.PinholePoseCal3_S2(pose_bc, cal))
        self._smart_noise = gtsam.noiseModel.Isotropic.Sigma(2, self.config.pixel_sigma_px)
        # landmark id -> (factor index in the smoother, the smart factor) in "smart" mode
        self._smart: dict[int, tuple[int, Any]] = {}
        self._initialized = False
        self._segment_id = 0  # the front end's map segment of the latest keyframe
        self._world_from_vo = np.eye(4)
        self._vo_scale = 1.0  # monocular: metres per VO unit
        self._monocular = not calibration.is_stereo
        self.last_scale = 0.0  # monocular: the start's scale tried at the latest keyframe, or 0
        self._init_keyframes: list[Keyframe] = []
        # monocular scale check: (t_ns, world_from_body) of recent keyframes, newest estimate
        self._kf_history: dict[int, np.ndarray] = {}
        self._last_scale_check_ns = 0
        # consecutive counted scale checks off beyond the tolerance on one side (signed)
        self._scale_check_streak = 0
        # monocular re-initialisation (``mono_reinit_residual_m``): True while the start is
        # redone (the front end's map is already in the world; it is scaled again)
        self._reinit = False
        self._restarts = 0  # re-initialisations the published estimates carry
        self._smoother: FixedLagSmoother | None = None
        self._values = gtsam.Values()
        self._states: list[_State] = []
        self._landmarks: set[int] = set()
        self._tracks: dict[int, list[_Obs]] = {}
        self._culled: set[int] = set()
        # last estimated position of every landmark that has been in the window (the map), and
        # the map landmarks that are variables in the window again
        self._positions: dict[int, np.ndarray] = {}
        self._map_alive: set[int] = set()
        self._map_prior = gtsam.noiseModel.Isotropic.Sigma(3, self.config.map_landmark_sigma_m)
        self._last_good: _GoodState | None = None
        self._t_origin_ns: int | None = None
        self._estimate = Estimate.pose_only(0, -1, np.eye(4), initialized=False)
        self.time_offset = OnlineTimeOffset(self.config) if self.config.time_offset_online else None
        self.intrinsics = (
            OnlineImuIntrinsics(self.config, calibration.imu)
            if self.config.imu_intrinsics_online
            else None
        )
        self._held: list[Keyframe] = []  # waiting for the time offset
        self._held_s = 0.0
        self.publish_inertial = publish_inertial
        self._inertial: list[KeyframeInertial] = []  # final states not yet taken

    # --- public API ------------------------------------------------------------------------------
    @property
    def initialized(self) -> bool:
        return self._initialized

    @property
    def world_from_vo(self) -> np.ndarray:
        """4x4 from the front end's VO frame to the back end's gravity-aligned world."""
        return self._world_from_vo.copy()

    def add_imu(self, sample: ImuSample) -> bool:
        """Buffer one IMU sample (False when rejected: non-finite, saturated, out of order)."""
        ok = self.imu.add(sample)
        if ok and self.time_offset is not None:
            self.time_offset.add_imu(sample)
        return ok

    def estimate(self) -> Estimate:
        """The latest published snapshot (immutable)."""
        return self._estimate

    def n_factors(self) -> int:
        """Factors currently held by the smoother (bounded by the lag)."""
        if self._smoother is None:
            return 0
        return int(self._smoother.getFactors().nrFactors())

    def add_keyframe(self, kf: Keyframe) -> Estimate | None:
        """Process one keyframe; returns the new estimate (initialised or not), or None while
        keyframes are held for the time offset (:meth:`_hold_for_time_offset`)."""
        t_start = time.perf_counter()
        cpu_start = time.thread_time()
        self.stats.keyframes += 1
        self.last_scale = 0.0
        to = self.time_offset
        est: Estimate | None = None
        if to is not None:
            to.add_keyframe(kf)
        if to is not None and self._hold_for_time_offset(kf):
            self._held.append(kf)
        else:
            if self._held:
                self._held_s += (kf.t_ns - self._held[0].t_ns) * 1e-9
            batch, self._held = [*self._held, kf], []
            est = self._fuse(batch)
        self.stats.update_times_s.append(time.perf_counter() - t_start)
        self.stats.update_cpu_s.append(time.thread_time() - cpu_start)
        self.stats.factor_counts.append(self.n_factors())
        return est

    def take_inertial(self, window: bool = False) -> tuple[KeyframeInertial, ...]:
        """The keyframe states the smoother let go since the last call (their last estimate and
        raw IMU readings from the state before; ``publish_inertial``), and with ``window``
        also those still in the window (the end of the run)."""
        out, self._inertial = self._inertial, []
        if window and self.publish_inertial and self._states and self._initialized:
            out += [self._inertial_of(s, self._values) for s in self._states]
        return tuple(out)

    def _inertial_of(self, s: _State, values: gtsam.Values) -> KeyframeInertial:
        bias = values.atConstantBias(B(s.k))
        pieces = s.raw_pieces
        if pieces is None:
            pieces = (np.zeros(0), np.zeros((0, 3)), np.zeros((0, 3)))
        return KeyframeInertial(
            s.keyframe_id,
            s.t_ns,
            np.asarray(values.atVector(V(s.k)), float),
            np.asarray(bias.gyroscope(), float),
            np.asarray(bias.accelerometer(), float),
            s.previous_keyframe_id if s.raw_pieces is not None else -1,
            *pieces,
        )

    def flush_held(self) -> Estimate | None:
        """Fuse the keyframes held for the time offset (the end of the input)."""
        if not self._held:
            return None
        batch, self._held = self._held, []
        return self._fuse(batch)

    def _fuse(self, batch: list[Keyframe]) -> Estimate | None:
        """Add keyframes in order; once the time offset is applied, held keyframes (and any
        stamped before the offset was known) go in the IMU clock. The newest estimate, with
        the offset's state, becomes the published one."""
        to = self.time_offset
        if to is not None and to.settled and self._initialized:
            batch = [_restamped(k, to.applied_ns) for k in batch]
        est: Estimate | None = None
        for k in batch:
            est = self._add_one(k) or est
        if to is not None and est is not None:
            est = dataclasses.replace(est, time_offset=to.state())
        if est is not None:
            self._estimate = est
        return est

    def _hold_for_time_offset(self, kf: Keyframe) -> bool:
        """Whether to hold ``kf`` back: once initialised and moving, until the time offset is
        known (about a second of motion), at most ``time_offset_hold_s`` per run. A second of
        aggressive motion fused with an unknown 20 ms offset bent the map for good (measured:
        ATE 0.5 -> 2.5 cm on 30 s of the aggressive profile); the front end runs on alone."""
        to = self.time_offset
        hold_s = self.config.time_offset_hold_s
        if to is None or to.settled or not self._initialized or hold_s <= 0:
            return False
        if not self._held and not to.moving:
            return False
        t0 = self._held[0].t_ns if self._held else kf.t_ns
        if self._held_s + (kf.t_ns - t0) * 1e-9 > hold_s:
            self._held_s = hold_s  # spent: never again this run
            return False
        if self._held and kf.segment_id != self._held[0].segment_id:
            return False
        self.stats.keyframes_held_for_time_offset += 1
        return True

    def _add_one(self, kf: Keyframe) -> Estimate | None:
        kf_pose_vo = _finite_pose(kf.world_from_body_vo)
        last_t_ns = self._states[-1].t_ns if self._initialized and self._states else -1
        if self._initialized and kf.t_ns <= last_t_ns:
            log.warning("keyframe %d ignored: its time is not after the last state", kf.keyframe_id)
            est = None
        elif not self._initialized:
            est = self._try_initialise(kf, kf_pose_vo)
        else:
            if kf.segment_id != self._segment_id:
                # a new VO map segment: relative VO poses across the boundary are meaningless
                self._states[-1].world_from_body_vo = None
            est = self._add_with_recovery(kf, kf_pose_vo)
            if self._monocular and self.config.mono_scale_check_window_s > 0:
                est = self._check_mono_scale(kf) or est
                if not self._initialized:  # re-initialising: the start is redone from here
                    est = self._try_initialise(kf, kf_pose_vo)
        self._segment_id = kf.segment_id
        return est

    def reset_from_last_good(self, reason: str = "requested") -> None:
        """Rebuild the smoother from the last good state with pose/velocity/bias priors."""
        good = self._last_good
        if good is None:
            raise SlamError("cannot reset the back end before it is initialised")
        self.stats.resets += 1
        msg = f"back end reset at keyframe {good.keyframe_id} ({reason})"
        log.warning(msg)
        if len(self.stats.failures) < 100:
            self.stats.failures.append(msg)
        self._start_smoother(
            good.k,
            good.keyframe_id,
            good.t_ns,
            good.pose,
            good.velocity,
            good.bias,
            good.world_from_body_vo,
        )
        self._last_good = good
        if good.keyframe is not None:
            self._add_observations_as_tracks(good.keyframe, good.k)

    # --- initialisation --------------------------------------------------------------------------
    def _uninitialised_estimate(self, kf: Keyframe, pose_vo: np.ndarray | None) -> Estimate:
        poses = {
            k.keyframe_id: k.world_from_body_vo
            for k in self._init_keyframes[-10:]
            if _finite_pose(k.world_from_body_vo) is not None
        }
        return Estimate(
            t_ns=kf.t_ns,
            keyframe_id=kf.keyframe_id,
            initialized=False,
            world_from_body=pose_vo if pose_vo is not None else np.eye(4),
            velocity_world_m_s=np.zeros(3),
            bias_gyro_rad_s=np.zeros(3),
            bias_accel_m_s2=np.zeros(3),
            keyframe_poses=poses,
            landmark_ids=np.zeros(0, np.int64),
            landmark_positions_world=np.zeros((0, 3)),
        )

    def _try_initialise(self, kf: Keyframe, pose_vo: np.ndarray | None) -> Estimate:
        if self._monocular:
            return self._try_mono_initialise(kf, pose_vo)
        cfg = self.config
        if kf.segment_id != self._segment_id:
            self._init_keyframes = []  # VO poses of different segments do not chain
        if pose_vo is None:
            return self._uninitialised_estimate(kf, None)
        self._init_keyframes.append(kf)
        self.imu.trim(self._init_keyframes[0].t_ns - int(2 * cfg.still_window_s * 1e9))
        if cfg.init_mode in ("auto", "still"):
            t, g, a = self.imu.arrays_between(kf.t_ns - int(cfg.still_window_s * 1e9), kf.t_ns)
            rate = self.imu_calibration.rate_hz
            if len(t) >= 0.9 * cfg.still_window_s * rate and is_still(g, a, cfg, rate):
                if cfg.still_init_method == "kalman":
                    res = still_init_kalman(g, a, self.imu_calibration)
                else:
                    res = still_init_align(g, a)
                up_vo = pose_vo[:3, :3] @ res.up_body
                self._world_from_vo = world_from_vo_gravity(up_vo, pose_vo[:3, 3])
                pose_w = self._world_from_vo @ pose_vo
                bias = make_bias(res.bias_gyro_rad_s, np.zeros(3))
                return self._finish_init(kf, pose_w, np.zeros(3), bias, "still")
        if cfg.init_mode in ("auto", "moving"):
            kfs = self._init_keyframes[-3 * cfg.moving_init_keyframes :]
            span_s = (kfs[-1].t_ns - kfs[0].t_ns) * 1e-9
            if len(kfs) >= cfg.moving_init_keyframes and span_s >= cfg.moving_init_min_span_s:
                res_m = self._moving_init(kfs)
                if res_m is not None:
                    self._world_from_vo = res_m.world_from_vo(kfs[0].world_from_body_vo[:3, 3])
                    pose_w = self._world_from_vo @ pose_vo
                    vel_w = self._world_from_vo[:3, :3] @ res_m.velocities_vo_m_s[-1]
                    bias = make_bias(res_m.bias_gyro_rad_s, res_m.bias_accel_m_s2)
                    return self._finish_init(kf, pose_w, vel_w, bias, "moving")
        self._init_keyframes = self._init_keyframes[-3 * cfg.moving_init_keyframes :]
        return self._uninitialised_estimate(kf, pose_vo)

    def _try_mono_initialise(self, kf: Keyframe, pose_vo: np.ndarray | None) -> Estimate:
        """Monocular start: the visual-inertial alignment of the newest keyframes' up-to-scale
        VO poses (``slam.backend.mono_init``); rejected, it is tried again at the next keyframe
        on a window that slides on. Accepted: the smoother starts at this keyframe, in the
        gravity-aligned metric world; every estimate carries the scale for the front end."""
        cfg = self.config
        if kf.segment_id != self._segment_id:
            self._init_keyframes = []  # a new map segment has its own scale
        if pose_vo is None:
            return self._uninitialised_estimate(kf, None)
        self._init_keyframes.append(kf)
        kfs = self._init_keyframes = self._init_keyframes[-3 * cfg.mono_init_keyframes :]
        self.imu.trim(kfs[0].t_ns - 1_000_000_000)
        self.stats.init_state = "initialising"
        max_scale_std = start_gate(len(kfs), (kfs[-1].t_ns - kfs[0].t_ns) * 1e-9, cfg)
        if max_scale_std is None:
            return self._uninitialised_estimate(kf, pose_vo)
        t, g, a = self.imu.arrays()
        body_from_cam0 = self._body_from_cam[0]
        points: dict[int, np.ndarray] = {}
        for k in kfs:  # the newest front-end position of each landmark
            points.update(zip(k.landmark_ids.tolist(), np.asarray(k.points_world_vo, float)))
        poses_vo = refine_vo_poses(
            np.array([k.world_from_body_vo for k in kfs]),
            [(np.asarray(k.landmark_ids), np.asarray(k.pixels_left_undist)) for k in kfs],
            points,
            self._k_mats[0],
            body_from_cam0,
            cfg.pixel_sigma_px,
        )
        res = align_mono(
            np.array([k.t_ns for k in kfs], dtype=np.int64),
            poses_vo,
            body_from_cam0,
            t,
            g,
            a,
            self.imu_calibration,
            cfg.imu_gap_max_s,
            cfg.mono_init_max_gravity_error,
            cfg.mono_init_max_scale_disagreement,
            accel_bias_sigma_m_s2=cfg.mono_init_accel_bias_sigma,
            max_scale_std=max_scale_std,
            retry_accel_bias_sigma_m_s2=cfg.mono_init_retry_accel_bias_sigma,
        )
        if res is None:
            return self._uninitialised_estimate(kf, pose_vo)
        self.last_scale = res.scale
        if len(self.stats.mono_init_attempts) < 200:
            self.stats.mono_init_attempts.append(
                {
                    "t_ns": kf.t_ns,
                    "keyframes": len(kfs),
                    "scale": round(res.scale, 5),
                    "scale_first_keyframes": round(res.scale_subset, 5),
                    "scale_std": round(res.scale_std, 5),
                    "max_scale_std": max_scale_std,
                    "gravity_norm_free_m_s2": round(res.gravity_norm_free_m_s2, 4),
                    "accel_bias_sigma_m_s2": res.accel_bias_sigma_m_s2,
                    "accepted": res.accepted,
                    "reason": res.reason,
                }
            )
        if not res.accepted:
            log.info("monocular alignment rejected at keyframe %d: %s", kf.keyframe_id, res.reason)
            return self._uninitialised_estimate(kf, pose_vo)
        scale = res.scale
        first_m = scale_body_pose(poses_vo[0], scale, body_from_cam0)
        self._world_from_vo = world_from_vo_gravity(-res.gravity_vo_m_s2, first_m[:3, 3])
        pose_w = self._world_from_vo @ scale_body_pose(poses_vo[-1], scale, body_from_cam0)
        vel_w = self._world_from_vo[:3, :3] @ res.velocities_vo_m_s[-1]
        bias = make_bias(res.bias_gyro_rad_s, res.bias_accel_m_s2)
        prior = None
        # a re-initialisation's window is always batch adjusted: the smoother it replaces
        # slipped within seconds of a start held by the loose ``prior_*`` sigmas
        if cfg.mono_init_batch and (
            self._reinit or not cfg.mono_init_batch_span_only or len(kfs) < cfg.mono_init_keyframes
        ):
            batch = self._batch_start(kfs, poses_vo, points, scale, res.velocities_vo_m_s, bias)
            if batch is not None:
                scale *= batch.scale_change
                pose_w = batch.world_from_body[-1]
                vel_w = batch.velocities_m_s[-1]
                bias = batch.biases[-1]
                prior = batch.prior
                newest = scale_body_pose(poses_vo[-1], scale, body_from_cam0)
                self._world_from_vo = pose_w @ invert_transform(newest)
        if self._reinit:
            # the front end's map is already in the world: it scales it by this again
            self._reinit = False
            self._restarts += 1
        self._vo_scale = scale
        self.stats.vo_scale = scale
        self.stats.init_state = "initialised"
        return self._finish_init(kf, pose_w, vel_w, bias, "mono", prior)

    def _batch_start(
        self,
        kfs: list[Keyframe],
        poses_vo: np.ndarray,
        points_vo: dict[int, np.ndarray],
        scale: float,
        velocities_vo_m_s: np.ndarray,
        bias: gtsam.imuBias.ConstantBias,
    ) -> Any:
        """``mono_init_batch``: the aligned window's visual-inertial bundle adjustment
        (:func:`slam.backend.mono_init.batch_start`) from the alignment's metric states; None
        (the alignment's start is used) when an interval has no IMU or the batch fails."""
        cfg = self.config
        b = self._body_from_cam[0]
        w_from_vo = self._world_from_vo
        poses_w = np.array([w_from_vo @ scale_body_pose(p, scale, b) for p in poses_vo])
        vels_w = np.asarray(velocities_vo_m_s, float) @ w_from_vo[:3, :3].T
        pims = []
        for k0, k1 in zip(kfs[:-1], kfs[1:], strict=True):
            pim = preintegrate(
                self.imu,
                self._params,
                bias,
                k0.t_ns,
                k1.t_ns,
                cfg.imu_gap_max_s,
                self.imu_calibration,
                (cfg.imu_gyro_scale_error, cfg.imu_accel_scale_error),
                cfg.imu_accel_scale_error_of_deviation,
                cfg.imu_accel_density_factor,
            )
            if pim is None:
                return None
            pims.append(pim)
        points_w = {
            lid: w_from_vo[:3, :3] @ (scale * np.asarray(p, float)) + w_from_vo[:3, 3]
            for lid, p in points_vo.items()
        }
        limit = cfg.max_landmarks_per_keyframe
        obs = [
            (np.asarray(k.landmark_ids)[:limit], np.asarray(k.pixels_left_undist)[:limit])
            for k in kfs
        ]
        batch = batch_start(
            poses_w,
            vels_w,
            bias,
            pims,
            obs,
            points_w,
            self._k_mats[0],
            b,
            (X(0), V(0), B(0)),
            cfg.pixel_sigma_px,
            cfg.huber_k,
            cfg.min_keyframes_per_landmark,
            (cfg.prior_pose_sigma_rad, cfg.prior_pose_sigma_m),
            (cfg.prior_bias_accel_sigma_m_s2, cfg.prior_bias_gyro_sigma_rad_s),
        )
        if batch is None:
            log.warning("monocular start: the window's batch adjustment failed; alignment kept")
            self.stats.mono_init_batch_scale_change = 1.0
            return None
        self.stats.mono_init_batch_scale_change = round(batch.scale_change, 5)
        sigma_v = float(np.sqrt(np.max(np.diag(batch.covariance)[6:9])))
        self.stats.mono_init_batch_velocity_sigma_m_s = round(sigma_v, 5)
        log.info(
            "monocular start: window batch adjustment over %d keyframes, %d landmarks: scale x%.4f,"
            " velocity sigma %.4f m/s",
            len(kfs),
            batch.landmarks,
            batch.scale_change,
            sigma_v,
        )
        return batch

    def _check_mono_scale(self, kf: Keyframe) -> Estimate | None:
        """Monocular: the start's visual-inertial alignment run again on the smoother's own
        keyframe estimates of the last ``mono_scale_check_window_s`` (metric: scale 1 if the
        smoother's scale agrees with the IMU). A counted check (the start's checks, standard
        deviation under ``mono_scale_check_max_std``) off by more than ``mono_scale_check_tolerance`` restarts
        the smoother at the newest state with the alignment's velocity, the recent estimates
        rescaled about it. Returns the new estimate when corrected."""
        cfg = self.config
        vals = self._values
        for s in self._states:
            self._kf_history[s.t_ns] = vals.atPose3(X(s.k)).matrix()
        window_ns = int(cfg.mono_scale_check_window_s * 1e9)
        reinit_ns = int(cfg.mono_reinit_window_s * 1e9) if cfg.mono_reinit_residual_m > 0 else 0
        keep_ns = max(window_ns, reinit_ns)
        self._kf_history = {t: p for t, p in self._kf_history.items() if t >= kf.t_ns - keep_ns}
        if kf.t_ns - self._last_scale_check_ns < int(cfg.mono_scale_check_every_s * 1e9):
            return None
        t, g, a = self.imu.arrays()
        if cfg.mono_scale_check_with_bias:
            a = a - vals.atConstantBias(B(self._states[-1].k)).accelerometer()
        if reinit_ns > 0 and self._check_for_reinit(kf, reinit_ns, t, g, a):
            return None
        window = self._history_window(kf.t_ns, window_ns)
        if window is None:
            return None
        self._last_scale_check_ns = kf.t_ns
        times, poses = window
        if cfg.mono_scale_check_method == "imu_fit":
            res = self._imu_fit(times, poses, t, g, a)
        else:
            res = check_scale(
                times,
                poses,
                self._body_from_cam[0],
                t,
                g,
                a,
                self.imu_calibration,
                cfg.imu_gap_max_s,
                cfg.mono_init_max_gravity_error,
                cfg.mono_init_max_scale_disagreement,
                cfg.mono_scale_check_max_std,
                cfg.mono_scale_check_tolerance,
            )
        if res is None:
            return None
        self._scale_check_streak = scale_check_streak(self._scale_check_streak, res)
        correct = res.wrong and abs(self._scale_check_streak) >= cfg.mono_scale_check_repeats
        if len(self.stats.mono_scale_checks) < 500:
            entry: dict[str, Any] = {
                "t_ns": kf.t_ns,
                "keyframes": len(times),
                "scale": round(res.scale, 4),
                "scale_std": round(res.scale_std, 4),
                "counted": res.counted,
                "corrected": correct,
            }
            if np.isfinite(res.residual_m):
                entry["residual_m"] = round(res.residual_m, 5)
            self.stats.mono_scale_checks.append(entry)
        if not correct:
            return None
        self._scale_check_streak = 0
        self.stats.mono_scale_corrections += 1
        last = self._states[-1]
        pose = vals.atPose3(X(last.k))
        centre = pose.translation()
        self._kf_history = {
            tt: _scaled_about(p, res.scale, centre) for tt, p in self._kf_history.items()
        }
        velocity = res.velocity_m_s
        msg = f"monocular scale check: {res.scale:.3f} at keyframe {kf.keyframe_id}, corrected"
        log.warning(msg)
        if len(self.stats.failures) < 100:
            self.stats.failures.append(msg)
        bias = vals.atConstantBias(B(last.k))
        self._start_smoother(
            last.k, last.keyframe_id, last.t_ns, pose, velocity, bias, last.world_from_body_vo
        )
        self._add_observations_as_tracks(kf, last.k)
        return self._make_estimate()

    def _history_window(self, t_ns: int, window_ns: int) -> tuple[np.ndarray, np.ndarray] | None:
        """The smoother's keyframe times and poses (``_kf_history``) of the last ``window_ns``
        before ``t_ns``; None until at least 6 of them span 0.8 of it."""
        times = np.array(sorted(tt for tt in self._kf_history if tt >= t_ns - window_ns), np.int64)
        if len(times) < 6 or (times[-1] - times[0]) < 0.8 * window_ns:
            return None
        return times, np.array([self._kf_history[int(tt)] for tt in times])

    def _imu_fit(
        self, times: np.ndarray, poses: np.ndarray, t: np.ndarray, g: np.ndarray, a: np.ndarray
    ) -> ScaleCheck | None:
        """:func:`slam.backend.mono_init.check_scale_by_imu_fit` of these keyframe poses, with
        the smoother's newest gyro bias and the scale check's limits."""
        cfg = self.config
        return check_scale_by_imu_fit(
            times,
            poses,
            t,
            g,
            a,
            self.imu_calibration,
            cfg.imu_gap_max_s,
            self._values.atConstantBias(B(self._states[-1].k)).gyroscope(),
            cfg.mono_scale_check_max_std,
            cfg.mono_scale_check_tolerance,
        )

    def _check_for_reinit(
        self, kf: Keyframe, window_ns: int, t: np.ndarray, g: np.ndarray, a: np.ndarray
    ) -> bool:
        """``mono_reinit_residual_m``: the smoother's keyframe positions of the last
        ``mono_reinit_window_s`` fitted to the IMU's trajectory
        (:func:`slam.backend.mono_init.check_scale_by_imu_fit`); a residual above the threshold
        re-initialises (:meth:`_reinitialise`, at most ``mono_reinit_max`` times). Its own
        window, shorter than the scale check's: the fit is due once the smoother's states span
        0.8 of it, so a slip 2-3.5 s after a start is seen within a second or two. Returns
        whether it re-initialised."""
        cfg = self.config
        window = self._history_window(kf.t_ns, window_ns)
        if window is None:
            return False
        self._last_scale_check_ns = kf.t_ns
        times, poses = window
        fit = self._imu_fit(times, poses, t, g, a)
        if fit is None or not np.isfinite(fit.residual_m):
            return False
        reinit = fit.residual_m > cfg.mono_reinit_residual_m
        reinit = reinit and self.stats.mono_reinits < cfg.mono_reinit_max
        if len(self.stats.mono_scale_checks) < 500:
            self.stats.mono_scale_checks.append(
                {
                    "t_ns": kf.t_ns,
                    "keyframes": len(times),
                    "residual_m": round(fit.residual_m, 5),
                    "reinit": reinit,
                }
            )
        if reinit:
            self._reinitialise(kf, fit.residual_m)
        return reinit

    def _reinitialise(self, kf: Keyframe, residual_m: float) -> None:
        """``mono_reinit_residual_m``: the smoother's recent positions are no similarity of the
        IMU's trajectory (``residual_m`` rms): its scale slipped, and no correction of its own
        states can say by how much (BENCHMARKS.md, scalecheck20). It is dropped and the monocular
        start's retry path takes over from this keyframe on (:meth:`_try_mono_initialise`, on
        the front end's keyframes from here, its window always batch adjusted); until a start
        is accepted the estimates are uninitialised, which the front end does not apply."""
        self.stats.mono_reinits += 1
        msg = (
            f"monocular scale check: IMU-fit residual {residual_m * 1e3:.1f} mm at keyframe "
            f"{kf.keyframe_id}, the start is redone"
        )
        log.warning(msg)
        if len(self.stats.failures) < 100:
            self.stats.failures.append(msg)
        self._initialized = False
        self._reinit = True
        self._smoother = None
        self._states = []
        self._landmarks = set()
        self._tracks = {}
        self._smart = {}
        self._map_alive = set()
        self._positions = {}  # the slipped smoother's landmarks: no map for the new start
        self._kf_history = {}
        self._scale_check_streak = 0
        self._init_keyframes = []
        self._last_good = None

    def _moving_init(self, kfs: list[Keyframe]) -> MovingInitResult | None:
        t, g, a = self.imu.arrays()
        res = moving_init(
            np.array([k.t_ns for k in kfs], dtype=np.int64),
            np.array([k.world_from_body_vo for k in kfs]),
            t,
            g,
            a,
            self.imu_calibration,
            self.config,
        )
        if res is None:
            return None
        g_err = abs(res.gravity_norm_unconstrained_m_s2 - self.imu_calibration.gravity_m_s2)
        if g_err > self.config.moving_init_max_gravity_error:
            log.info("moving-start init rejected: |g| error %.3f m/s^2", g_err)
            return None
        return res

    def _finish_init(
        self,
        kf: Keyframe,
        pose_w: np.ndarray,
        vel_w: np.ndarray,
        bias: gtsam.imuBias.ConstantBias,
        method: str,
        prior: gtsam.NonlinearFactor | None = None,
    ) -> Estimate:
        self._initialized = True
        self.stats.init_method = method
        if self.stats.init_t_ns < 0:  # the first start's (a re-initialisation keeps it)
            self.stats.init_t_ns = kf.t_ns
        self._t_origin_ns = kf.t_ns
        self._init_keyframes = []
        log.info("back end initialised (%s start) at keyframe %d", method, kf.keyframe_id)
        self._start_smoother(
            0,
            kf.keyframe_id,
            kf.t_ns,
            gtsam.Pose3(pose_w),
            vel_w,
            bias,
            kf.world_from_body_vo,
            prior,
        )
        self._last_good.keyframe = kf  # type: ignore[union-attr]
        self._add_observations_as_tracks(kf, 0)
        return self._make_estimate()

    # --- smoother plumbing -----------------------------------------------------------------------
    def _t_rel_s(self, t_ns: int) -> float:
        assert self._t_origin_ns is not None
        return (t_ns - self._t_origin_ns) * 1e-9

    def _smoother_update(
        self,
        graph: gtsam.NonlinearFactorGraph,
        values: gtsam.Values,
        stamps: dict[int, float],
        remove: list[int] | None = None,
    ) -> None:
        """One smoother update (a seam for tests to inject failures)."""
        self._live_smoother().update(graph, values, stamps, remove or [])

    def _live_smoother(self) -> FixedLagSmoother:
        if self._smoother is None:
            raise RuntimeError("smoother used before initialisation")
        return self._smoother

    def _start_smoother(
        self,
        k: int,
        keyframe_id: int,
        t_ns: int,
        pose: gtsam.Pose3,
        velocity: np.ndarray,
        bias: gtsam.imuBias.ConstantBias,
        pose_vo: np.ndarray | None,
        prior: gtsam.NonlinearFactor | None = None,
    ) -> None:
        """A new smoother at state ``k``, held by ``prior`` (on its pose, velocity and bias
        keys) or else by the config's ``prior_*`` sigmas about the given values."""
        cfg = self.config
        params = gtsam.ISAM2Params()
        params.setRelinearizeThreshold(cfg.relinearize_threshold)
        params.relinearizeSkip = 1
        # reuse the slots of removed/marginalised factors: otherwise the factor array grows by
        # every factor ever added (measured: +54 MB RSS over a 20-minute run)
        params.findUnusedFactorSlots = True
        self._smoother = FixedLagSmoother(cfg.lag_s, params)
        graph = gtsam.NonlinearFactorGraph()
        if prior is not None:
            graph.add(prior)
        else:
            graph.add(
                gtsam.PriorFactorPose3(
                    X(k), pose, pose_noise(cfg.prior_pose_sigma_rad, cfg.prior_pose_sigma_m)
                )
            )
            graph.add(
                gtsam.PriorFactorVector(
                    V(k),
                    np.asarray(velocity, float),
                    gtsam.noiseModel.Isotropic.Sigma(3, cfg.prior_velocity_sigma_m_s),
                )
            )
            graph.add(
                gtsam.PriorFactorConstantBias(
                    B(k),
                    bias,
                    bias_noise(cfg.prior_bias_accel_sigma_m_s2, cfg.prior_bias_gyro_sigma_rad_s),
                )
            )
        values = gtsam.Values()
        values.insert(X(k), pose)
        values.insert(V(k), np.asarray(velocity, float))
        values.insert(B(k), bias)
        t = self._t_rel_s(t_ns)
        self._smoother.update(graph, values, {X(k): t, V(k): t, B(k): t}, [])
        self._values = self._live_smoother().calculateEstimate()
        self._states = [_State(k, keyframe_id, t_ns, pose_vo)]
        self._landmarks = set()
        self._tracks = {}
        self._smart = {}
        self._map_alive = set()
        self._last_good = _GoodState(
            k, keyframe_id, t_ns, pose, np.asarray(velocity, float), bias, pose_vo
        )

    def _add_observations_as_tracks(self, kf: Keyframe, k: int) -> None:
        for lid, uv_l, uv_r in _observations(kf, self.config.max_landmarks_per_keyframe):
            if lid not in self._culled:
                self._tracks.setdefault(lid, []).append(_Obs(k, uv_l, uv_r))

    def _add_with_recovery(self, kf: Keyframe, pose_vo: np.ndarray | None) -> Estimate:
        for attempt in range(3):
            try:
                self._add_state(kf, pose_vo, with_visual=attempt == 0)
                return self._make_estimate()
            except (RuntimeError, EstimatorFailure) as exc:
                first_line = (str(exc).strip().splitlines() or [""])[0][:120]
                self.reset_from_last_good(f"{type(exc).__name__}: {first_line}")
        # three failures in a row: keep the last good state, publish it, and move on
        return self._make_estimate()

    def _add_state(self, kf: Keyframe, pose_vo: np.ndarray | None, with_visual: bool) -> None:
        cfg = self.config
        prev = self._states[-1]
        k = prev.k + 1
        vals = self._values
        prev_pose = vals.atPose3(X(prev.k))
        prev_vel = vals.atVector(V(prev.k))
        prev_bias = vals.atConstantBias(B(prev.k))
        graph = gtsam.NonlinearFactorGraph()
        new_values = gtsam.Values()
        pim = preintegrate(
            self.imu,
            self._params,
            prev_bias,
            prev.t_ns,
            kf.t_ns,
            cfg.imu_gap_max_s,
            self.imu_calibration,
            self._scale_errors(),
            cfg.imu_accel_scale_error_of_deviation,
            cfg.imu_accel_density_factor,
        )
        raw_pieces = None
        if (self.intrinsics is not None or self.publish_inertial) and pim is not None:
            raw_pieces = integration_pieces(
                *self.imu.raw_arrays(), prev.t_ns, kf.t_ns, cfg.imu_gap_max_s
            )
        if pim is not None:
            pred = pim.predict(gtsam.NavState(prev_pose, prev_vel), prev_bias)
            pose_guess, vel_guess = pred.pose(), pred.velocity()
            graph.add(
                gtsam.CombinedImuFactor(X(prev.k), V(prev.k), X(k), V(k), B(prev.k), B(k), pim)
            )
        else:
            self.imu.stats.intervals_without_imu += 1
            dt = max((kf.t_ns - prev.t_ns) * 1e-9, 1e-3)
            if pose_vo is not None and prev.world_from_body_vo is not None:
                rel = gtsam.Pose3(invert_transform(prev.world_from_body_vo) @ pose_vo)
            else:  # no IMU and no VO: constant velocity guess, very weak
                rel = gtsam.Pose3(gtsam.Rot3(), prev_pose.rotation().unrotate(prev_vel * dt))
            pose_guess = prev_pose.compose(rel)
            vel_guess = prev_vel
            graph.add(
                gtsam.BetweenFactorPose3(
                    X(prev.k),
                    X(k),
                    rel,
                    pose_noise(cfg.no_imu_pose_sigma_rad, cfg.no_imu_pose_sigma_m),
                )
            )
            graph.add(
                gtsam.BetweenFactorVector(
                    V(prev.k),
                    V(k),
                    np.zeros(3),
                    gtsam.noiseModel.Isotropic.Sigma(3, cfg.no_imu_velocity_sigma_m_s),
                )
            )
            imu = self.imu_calibration
            graph.add(
                gtsam.BetweenFactorConstantBias(
                    B(prev.k),
                    B(k),
                    make_bias(np.zeros(3), np.zeros(3)),
                    bias_noise(
                        imu.accel_random_walk * np.sqrt(dt), imu.gyro_random_walk * np.sqrt(dt)
                    ),
                )
            )
        new_values.insert(X(k), pose_guess)
        new_values.insert(V(k), vel_guess)
        new_values.insert(B(k), prev_bias)
        t = self._t_rel_s(kf.t_ns)
        stamps: dict[int, float] = {X(k): t, V(k): t, B(k): t}

        # visual factors
        window_ks = {s.k for s in self._states} | {k}
        poses = {s.k: self._cams_from_world(vals.atPose3(X(s.k)).matrix()) for s in self._states}
        poses[k] = self._cams_from_world(pose_guess.matrix())
        factor_lids: list[int] = []  # landmark id of each new visual factor, -1 for others
        factor_lids += [-1] * graph.size()
        new_landmark_ids: set[int] = set()
        remove: list[int] = []
        smart_new: dict[int, Any] = {}
        new_map: set[int] = set()
        handled: set[int] = set()
        if with_visual and cfg.map_landmarks:
            handled = self._map_visual(kf, k, graph, new_values, stamps, t, factor_lids, new_map)
        if with_visual and cfg.landmark_model == "smart":
            remove = self._smart_visual(
                kf, k, graph, poses, window_ks, factor_lids, smart_new, handled
            )
        elif with_visual:
            gate_px = 2.0 * cfg.outlier_reprojection_px
            for lid, uv_l, uv_r in _observations(kf, cfg.max_landmarks_per_keyframe):
                if lid in self._culled or lid in handled:
                    continue
                if lid in self._landmarks:
                    p_w = vals.atPoint3(L(lid))
                    err = self._reprojection_errors(poses[k], p_w, uv_l, uv_r)
                    if not np.all(err < gate_px):
                        self.stats.observations_gated += 1
                        continue
                    self._add_projection(graph, k, lid, uv_l, uv_r, factor_lids)
                    stamps[L(lid)] = t
                    continue
                track = self._tracks.setdefault(lid, [])
                track = [o for o in track if o.k in window_ks]
                track.append(_Obs(k, uv_l, uv_r))
                self._tracks[lid] = track
                if len({o.k for o in track}) < cfg.min_keyframes_per_landmark:
                    continue
                p_tri = self._triangulate(track, poses)
                if p_tri is None:
                    if len(track) > 4:
                        self._culled.add(lid)
                        self._tracks.pop(lid, None)
                    continue
                new_values.insert(L(lid), p_tri)
                stamps[L(lid)] = t
                for o in track:
                    self._add_projection(graph, o.k, lid, o.uv_left, o.uv_right, factor_lids)
                new_landmark_ids.add(lid)
                self._tracks.pop(lid, None)
        else:
            self.stats.keyframes_without_visual += 1
        self._smoother_update(graph, new_values, stamps, remove)
        new_indices = list(self._live_smoother().getISAM2Result().getNewFactorsIndices())
        for _ in range(cfg.extra_iterations):
            self._smoother_update(gtsam.NonlinearFactorGraph(), gtsam.Values(), {})
        values = self._live_smoother().calculateEstimate()
        self._check_state(values, k, pose_guess, vel_guess, imu_ok=pim is not None)

        # accepted: commit bookkeeping
        self._values = values
        self._landmarks |= new_landmark_ids
        self.stats.landmarks_inserted += len(new_landmark_ids)
        self.stats.observations_added += sum(1 for x in factor_lids if x >= 0)
        self._states.append(
            _State(k, kf.keyframe_id, kf.t_ns, pose_vo, raw_pieces, prev.keyframe_id)
        )
        if self.intrinsics is not None:
            self._fit_intrinsics(vals, values)
        if self.publish_inertial:
            self._inertial += [
                self._inertial_of(st, vals)
                for st in self._states
                if not values.exists(X(st.k)) and vals.exists(X(st.k))
            ]
        self._states = [s for s in self._states if values.exists(X(s.k))]
        self._landmarks = {lid for lid in self._landmarks if values.exists(L(lid))}
        self._map_alive = {lid for lid in self._map_alive | new_map if values.exists(L(lid))}
        self.stats.map_landmarks_inserted += len(new_map)
        oldest_k = self._states[0].k
        for lid in list(self._tracks):
            tr = [o for o in self._tracks[lid] if o.k >= oldest_k]
            if tr:
                self._tracks[lid] = tr
            else:
                del self._tracks[lid]
        if smart_new:
            for lid, idx in zip(factor_lids, new_indices):
                if lid in smart_new:
                    self._smart[lid] = (idx, smart_new[lid])
            self._smart = {
                lid: v for lid, v in self._smart.items() if lid in self._tracks or lid in smart_new
            }
        elif with_visual and cfg.landmark_model == "projection":
            self._cull_outliers(values, k, factor_lids, new_indices, new_landmark_ids)
        self._last_good = _GoodState(
            k,
            kf.keyframe_id,
            kf.t_ns,
            values.atPose3(X(k)),
            values.atVector(V(k)),
            values.atConstantBias(B(k)),
            pose_vo,
            kf,
        )
        keep_s = 1.0
        if self._monocular:
            keep_s += self.config.mono_scale_check_window_s
        self.imu.trim(self._states[0].t_ns - int(keep_s * 1e9))

    def _map_visual(
        self,
        kf: Keyframe,
        k: int,
        graph: gtsam.NonlinearFactorGraph,
        new_values: gtsam.Values,
        stamps: dict[int, float],
        t: float,
        factor_lids: list[int],
        new_map: set[int],
    ) -> set[int]:
        """Observations of landmarks that left the window and are seen again (the front end
        found them in its map): each comes back as a variable ``L(id)`` held by a prior at its
        last estimated position (``map_landmark_sigma_m``), with projection factors, so a
        revisit pulls the window onto the old landmarks instead of re-triangulating them from
        drifted poses (VINS-Fusion's and Basalt's map-based relocalisation do the like with
        keyframe poses). Returns the landmark ids handled here."""
        handled: set[int] = set()
        for lid, uv_l, uv_r in _observations(kf, len(kf.landmark_ids)):
            if len(handled) >= self.config.max_map_landmarks_per_keyframe:
                break
            if lid in self._culled:
                continue
            if lid in self._map_alive:
                pass
            elif lid in self._tracks or lid in self._landmarks or lid in self._smart:
                continue  # still in the window: a plain landmark
            else:
                pos = self._positions.get(lid)
                if pos is None:
                    continue
                new_values.insert(L(lid), pos)
                graph.add(gtsam.PriorFactorPoint3(L(lid), pos, self._map_prior))
                factor_lids.append(-1)
                new_map.add(lid)
                # stamped once: it leaves with the lag even while still seen (then comes back
                # with a new prior); kept alive, its marginals would link ever more states
                stamps[L(lid)] = t
            self._add_projection(graph, k, lid, uv_l, uv_r, factor_lids)
            self.stats.map_observations += 1
            handled.add(lid)
        return handled

    def _smart_visual(
        self,
        kf: Keyframe,
        k: int,
        graph: gtsam.NonlinearFactorGraph,
        poses: dict[int, list[np.ndarray]],
        window_ks: set[int],
        factor_lids: list[int],
        smart_new: dict[int, Any],
        handled: set[int],
    ) -> list[int]:
        """Smart stereo-rig factors: one per landmark, rebuilt with every new observation (the
        previous one is removed). Returns the factor indices to remove."""
        cfg = self.config
        gate_px = 2.0 * cfg.outlier_reprojection_px
        existing = self._live_smoother().getFactors()
        remove: list[int] = []
        for lid, uv_l, uv_r in _observations(kf, cfg.max_landmarks_per_keyframe):
            if lid in self._culled or lid in handled:
                continue
            prev = self._smart.get(lid)
            track = [o for o in self._tracks.get(lid, []) if o.k in window_ks]
            if prev is not None:
                # slots are reused (findUnusedFactorSlots): the index must still hold *our* factor
                prev_factor: Any = prev[1]
                alive = bool(existing.exists(prev[0]) and existing.at(prev[0]) is prev_factor)
                if not alive:
                    # its factor was marginalised (its information is in the marginal prior):
                    # start a fresh track so no observation is counted twice
                    del self._smart[lid]
                    prev = None
                    track = []
                else:
                    res = prev_factor.point()
                    if res.valid() and not self._gate_ok(poses[k], res.get(), uv_l, uv_r, gate_px):
                        self.stats.observations_gated += 1
                        continue
            track.append(_Obs(k, uv_l, uv_r))
            self._tracks[lid] = track
            if len({o.k for o in track}) < cfg.min_keyframes_per_landmark:
                continue
            factor = gtsam.SmartProjectionRigFactorPinholePoseCal3_S2(
                self._smart_noise, self._rig, self._smart_params
            )
            meas, keys, cam_ids = [], [], []
            for o in track:
                key = X(o.k)
                meas.append(o.uv_left)
                keys.append(key)
                cam_ids.append(0)
                if o.uv_right is not None and cfg.right_camera_factors:
                    meas.append(o.uv_right)
                    keys.append(key)
                    cam_ids.append(1)
            factor.add(meas, keys, cam_ids)
            graph.add(factor)
            factor_lids.append(lid)
            smart_new[lid] = factor
            if prev is None:
                self.stats.landmarks_inserted += 1
            else:
                remove.append(prev[0])
        return remove

    def _add_projection(
        self,
        graph: gtsam.NonlinearFactorGraph,
        k: int,
        lid: int,
        uv_l: np.ndarray,
        uv_r: np.ndarray | None,
        factor_lids: list[int],
    ) -> None:
        graph.add(
            gtsam.GenericProjectionFactorCal3_S2(
                uv_l, self._pixel_noise, X(k), L(lid), self._cal[0], self._body_p_cam[0]
            )
        )
        factor_lids.append(lid)
        if uv_r is not None and len(self._cal) > 1 and self.config.right_camera_factors:
            graph.add(
                gtsam.GenericProjectionFactorCal3_S2(
                    uv_r, self._pixel_noise, X(k), L(lid), self._cal[1], self._body_p_cam[1]
                )
            )
            factor_lids.append(lid)

    def _gate_ok(
        self,
        cams_from_world: list[np.ndarray],
        p_w: np.ndarray,
        uv_l: np.ndarray,
        uv_r: np.ndarray | None,
        gate_px: float,
    ) -> bool:
        """Cheap scalar check that an observation reprojects within ``gate_px`` (left camera)."""
        c = cams_from_world[0]
        x = c[0, 0] * p_w[0] + c[0, 1] * p_w[1] + c[0, 2] * p_w[2] + c[0, 3]
        y = c[1, 0] * p_w[0] + c[1, 1] * p_w[1] + c[1, 2] * p_w[2] + c[1, 3]
        z = c[2, 0] * p_w[0] + c[2, 1] * p_w[1] + c[2, 2] * p_w[2] + c[2, 3]
        if z < self.config.min_depth_m:
            return False
        kmat = self._k_mats[0]
        du = kmat[0, 0] * x / z + kmat[0, 2] - uv_l[0]
        dv = kmat[1, 1] * y / z + kmat[1, 2] - uv_l[1]
        return bool(du * du + dv * dv < gate_px * gate_px)

    def _cams_from_world(self, world_from_body: np.ndarray) -> list[np.ndarray]:
        """cam_from_world (4x4) of every camera for one body pose."""
        return [invert_transform(world_from_body @ b) for b in self._body_from_cam]

    def _reprojection_errors(
        self,
        cams_from_world: list[np.ndarray],
        p_w: np.ndarray,
        uv_l: np.ndarray,
        uv_r: np.ndarray | None,
    ) -> np.ndarray:
        """Pixel errors of one landmark in the left (and right) camera; inf if behind."""
        out = []
        for cam, uv in ((0, uv_l), (1, uv_r)):
            if uv is None or cam >= len(self._cal):
                continue
            cam_from_world = cams_from_world[cam]
            pc = cam_from_world[:3, :3] @ p_w + cam_from_world[:3, 3]
            if pc[2] < self.config.min_depth_m:
                out.append(np.inf)
                continue
            proj = self._k_mats[cam] @ (pc / pc[2])
            out.append(float(np.hypot(proj[0] - uv[0], proj[1] - uv[1])))
        return np.asarray(out)

    def _triangulate(
        self, track: list[_Obs], poses: dict[int, list[np.ndarray]]
    ) -> np.ndarray | None:
        """Linear (DLT) triangulation from every left/right view, then checks depth and error."""
        rows = []
        views = []
        for o in track:
            for cam, uv in ((0, o.uv_left), (1, o.uv_right)):
                if uv is None or cam >= len(self._cal):
                    continue
                cam_from_world = poses[o.k][cam]
                xn = np.linalg.solve(self._k_mats[cam], np.array([uv[0], uv[1], 1.0]))
                p = cam_from_world[:3, :]
                rows.append(xn[0] * p[2] - p[0])
                rows.append(xn[1] * p[2] - p[1])
                views.append(o)
        if len(rows) < 4:
            return None
        _, _, vt = np.linalg.svd(np.asarray(rows))
        h = vt[-1]
        if abs(h[3]) < 1e-12:
            return None
        p_w = h[:3] / h[3]
        for o in track:
            err = self._reprojection_errors(poses[o.k], p_w, o.uv_left, o.uv_right)
            if not np.all(err < self.config.outlier_reprojection_px):
                return None
            cam_from_world = poses[o.k][0]
            depth = np.linalg.norm(cam_from_world[:3, :3] @ p_w + cam_from_world[:3, 3])
            if depth > self.config.max_depth_m:
                return None
        return p_w

    def _scale_errors(self) -> tuple[float, float]:
        """The scale / axis error the IMU noise allows for, per sensor (gyro, accel): the
        configured ones, or ``imu_intrinsics_scale_error`` once that sensor's matrix is applied."""
        cfg = self.config
        gyro, accel = cfg.imu_gyro_scale_error, cfg.imu_accel_scale_error
        est = self.intrinsics
        if est is not None:
            if est.gyro_applied_t_ns >= 0:
                gyro = cfg.imu_intrinsics_scale_error
            if est.accel_applied_t_ns >= 0:
                accel = cfg.imu_intrinsics_scale_error
        return gyro, accel

    def _fit_intrinsics(self, before: gtsam.Values, after: gtsam.Values) -> None:
        """Hand the states this update marginalised (their last estimate, from ``before``) to
        the IMU intrinsics' fit; apply what it returns to the back end's IMU readings."""
        assert self.intrinsics is not None
        for s in self._states:
            if after.exists(X(s.k)) or not before.exists(X(s.k)):
                continue
            pose = before.atPose3(X(s.k))
            self.intrinsics.add_state(
                KeyframeState(
                    s.t_ns,
                    pose.rotation().matrix(),
                    np.asarray(pose.translation(), float),
                    np.asarray(before.atVector(V(s.k)), float),
                    s.raw_pieces,
                )
            )
        applied = self.intrinsics.update()
        if applied is not None:
            self.imu.set_intrinsics(applied)

    def _check_state(
        self,
        values: gtsam.Values,
        k: int,
        pose_guess: gtsam.Pose3,
        vel_guess: np.ndarray,
        imu_ok: bool,
    ) -> None:
        cfg = self.config
        pose = values.atPose3(X(k))
        vel = values.atVector(V(k))
        bias = values.atConstantBias(B(k))
        pos = pose.translation()
        bg, ba = bias.gyroscope(), bias.accelerometer()
        if not (
            np.all(np.isfinite(pos))
            and np.all(np.isfinite(vel))
            and np.all(np.isfinite(bg))
            and np.all(np.isfinite(ba))
        ):
            raise EstimatorFailure("non-finite state")
        if np.linalg.norm(vel) > cfg.max_velocity_m_s:
            raise EstimatorFailure(f"velocity {np.linalg.norm(vel):.1f} m/s")
        if (
            np.linalg.norm(bg) > cfg.max_bias_gyro_rad_s
            or np.linalg.norm(ba) > cfg.max_bias_accel_m_s2
        ):
            raise EstimatorFailure("bias out of range")
        if imu_ok:
            if np.linalg.norm(vel - vel_guess) > cfg.max_velocity_jump_m_s:
                raise EstimatorFailure("velocity jump")
            if np.linalg.norm(pos - pose_guess.translation()) > cfg.max_position_jump_m:
                raise EstimatorFailure("position jump")

    def _cull_outliers(
        self,
        values: gtsam.Values,
        k: int,
        factor_lids: list[int],
        indices: list[int],
        new_landmarks: set[int],
    ) -> None:
        """After optimisation: newest observations with a large error are removed (landmark culled)."""
        if len(indices) != len(factor_lids):
            return
        graph = self._live_smoother().getFactors()
        bad_idx: list[int] = []
        bad_lids: set[int] = set()
        thr2 = self.config.outlier_reprojection_px**2
        for lid, idx in zip(factor_lids, indices):
            if lid < 0 or not graph.exists(idx):
                continue
            f = cast(Any, graph.at(idx))
            # the unwhitened residual is the reprojection error in pixels (Huber-independent)
            try:
                r = f.unwhitenedError(values)
            except RuntimeError:
                r = np.array([np.inf, np.inf])
            if float(r @ r) > thr2:
                bad_lids.add(lid)
                if lid not in new_landmarks and f.keys()[0] == X(k):
                    bad_idx.append(idx)
        if not bad_lids:
            return
        self._culled |= bad_lids
        self.stats.landmarks_culled += len(bad_lids)
        if bad_idx:
            self._smoother_update(gtsam.NonlinearFactorGraph(), gtsam.Values(), {}, bad_idx)
            self.stats.observations_removed += len(bad_idx)
            self._values = self._live_smoother().calculateEstimate()

    def _make_estimate(self) -> Estimate:
        vals = self._values
        last = self._states[-1]
        pose = vals.atPose3(X(last.k)).matrix()
        bias = vals.atConstantBias(B(last.k))
        if self.config.landmark_model == "smart":
            found = []
            for lid, (_, factor) in self._smart.items():
                res = factor.point()
                if res.valid():
                    found.append((lid, res.get()))
            found.sort(key=lambda x: x[0])
            lids = np.array([f[0] for f in found], dtype=np.int64)
            pts = np.array([f[1] for f in found]).reshape(-1, 3)
        else:
            lids = np.array(sorted(self._landmarks), dtype=np.int64)
            pts = np.array([vals.atPoint3(L(int(i))) for i in lids]).reshape(-1, 3)
        for lid, p in zip(lids.tolist(), pts, strict=True):
            self._positions[lid] = p  # a map landmark's own entry stays its first estimate
        if self._map_alive:
            alive = sorted(self._map_alive)
            lids = np.concatenate([lids, np.asarray(alive, np.int64)])
            pts = np.vstack([pts, [vals.atPoint3(L(i)) for i in alive]])
        return Estimate(
            t_ns=last.t_ns,
            keyframe_id=last.keyframe_id,
            initialized=True,
            world_from_body=pose,
            velocity_world_m_s=np.asarray(vals.atVector(V(last.k)), float),
            bias_gyro_rad_s=np.asarray(bias.gyroscope(), float),
            bias_accel_m_s2=np.asarray(bias.accelerometer(), float),
            keyframe_poses={s.keyframe_id: vals.atPose3(X(s.k)).matrix() for s in self._states},
            landmark_ids=lids,
            landmark_positions_world=pts,
            vo_scale=self._vo_scale,
            restarts=self._restarts,
            imu_intrinsics=None
            if self.intrinsics is None or self.intrinsics.applied.is_identity
            else self.intrinsics.applied,
        )


def _restamped(kf: Keyframe, offset_ns: int) -> Keyframe:
    """``kf`` stamped with the camera-IMU offset ``offset_ns`` instead of the one it carries."""
    if kf.time_offset_ns == offset_ns:
        return kf
    t_ns = kf.t_ns - kf.time_offset_ns + offset_ns
    return dataclasses.replace(kf, t_ns=t_ns, time_offset_ns=offset_ns)


def _scaled_about(world_from_body: np.ndarray, scale: float, centre: np.ndarray) -> np.ndarray:
    """The pose with its position scaled by ``scale`` about ``centre`` (world frame)."""
    out = np.array(world_from_body, dtype=float)
    out[:3, 3] = centre + scale * (out[:3, 3] - centre)
    return out


def _finite_pose(pose: np.ndarray | None) -> np.ndarray | None:
    """The pose as a float 4x4 if it is a finite rigid transform, else None."""
    if pose is None:
        return None
    m = np.asarray(pose, dtype=float)
    if m.shape != (4, 4) or not np.all(np.isfinite(m)):
        return None
    r = m[:3, :3]
    if not np.allclose(r.T @ r, np.eye(3), atol=1e-4):
        return None
    return m


def _observations(kf: Keyframe, limit: int) -> list[tuple[int, np.ndarray, np.ndarray | None]]:
    """(landmark id, left uv, right uv or None) for the finite observations of a keyframe."""
    ids = np.asarray(kf.landmark_ids, dtype=np.int64)
    left = np.asarray(kf.pixels_left_undist, dtype=float).reshape(-1, 2)
    right = np.asarray(kf.pixels_right_undist, dtype=float).reshape(-1, 2)
    ok_l = np.all(np.isfinite(left), axis=1)
    ok_r = (
        np.all(np.isfinite(right), axis=1) if len(right) == len(ids) else np.zeros(len(ids), bool)
    )
    out = []
    for i in np.flatnonzero(ok_l)[:limit]:
        out.append((int(ids[i]), left[i], right[i] if ok_r[i] else None))
    return out

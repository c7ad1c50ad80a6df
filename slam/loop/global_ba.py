"""Global bundle adjustment over all keyframes after loop closure (ORB-SLAM's "full BA").

Why: pose-graph optimisation only moves keyframes as rigid nodes along their odometry edges,
so after a revisit the first pass's own odometry error stays in the map (every later pass is
pulled onto it). Measured by re-optimising runs' pose graphs (``loop.debug_graph``) with the
loop edges replaced by ground-truth relative poses: keyframe ATE no lower than 5.4 mm on
room-loop (odometry 12.8 mm), 5.1 mm on room-figure8 (7.6 mm), 14.3 mm on the hall (36 mm). Here every stereo
observation of the run is re-used: landmarks that a verified loop matched between the query
and the candidate keyframe, and those the caller's fusion search matched between any keyframe
and the other passes near it (``LoopCloser._fusion_pairs``), are *fused* into one, so the
revisit's observations and the first pass's constrain the same points, and all keyframe poses
and landmarks are re-estimated together.

Problem: one Pose3 (world_from_body) per keyframe, one Point3 per (fused) landmark seen in at
least ``min_keyframes`` keyframes, Huber-robust ``GenericProjectionFactorCal3_S2`` for the left
and (where matched) right undistorted pixel, the odometry edges of the pose graph as weak
``BetweenFactorPose3`` (they carry the IMU's gravity direction and smoothness; the pose graph's
sigmas, scaled by ``odometry_sigma_scale``, behind a Huber kernel), and weak priors on every
keyframe's starting pose as the gauge.
Levenberg-Marquardt, then observations reprojecting worse than ``outlier_sigmas`` robust
sigmas of the round's errors (at most ``outlier_px``) are dropped and it runs again (with
``keyframe_sigma_max`` > 1, keyframes noisier than the round weighed by their own errors). Written
with GTSAM's factors because no Python library does stereo-rig BA with relative-pose priors;
the data handling is numpy.
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from typing import Literal

import gtsam
import numpy as np

from slam.backend.imu import integrate_pieces, make_bias, preintegration_params, scale_error_params
from slam.backend.imu_intrinsics import KeyframeState, fit_intrinsics
from slam.core.calibration import Calibration, ImuCalibration
from slam.core.messages import ImuIntrinsics, KeyframeInertial
from slam.posegraph import PoseEdge, gaussian_from_g2o_information


def _pose_key(kf_id: int) -> int:
    return int(gtsam.symbol("x", kf_id))


def _velocity_key(kf_id: int) -> int:
    return int(gtsam.symbol("v", kf_id))


def _bias_key(kf_id: int) -> int:
    return int(gtsam.symbol("b", kf_id))


def _point_key(index: int) -> int:
    return int(gtsam.symbol("l", index))


def _point_keys(indices: np.ndarray) -> list[int]:
    """``_point_key`` of many indices at once (GTSAM's symbol: the character in the top 8
    bits, the index below)."""
    return ((ord("l") << 56) + np.asarray(indices, dtype=np.uint64)).tolist()


@dataclass(frozen=True, eq=False)
class KeyframeObservations:
    """A keyframe's landmark observations, kept for the global adjustment.

    ``left_px``/``right_px`` (N, 2): undistorted pixels (``Keyframe`` convention; right rows NaN
    without a stereo match); ``points_cam0`` (N, 3): the front end's landmark positions in this
    keyframe's cam0 frame (initial guesses; NaN when unknown).
    """

    landmark_ids: np.ndarray
    left_px: np.ndarray
    right_px: np.ndarray
    points_cam0: np.ndarray


@dataclass(frozen=True)
class GlobalBaParams:
    pixel_sigma_px: float = 0.3
    huber_k: float = 1.345
    """Huber threshold in standard deviations."""
    min_keyframes: int = 2
    """Landmarks seen (after fusion) in fewer keyframes are left out."""
    max_depth_m: float = 30.0
    """Initial guesses farther than this from their first keyframe are left out."""
    outlier_px: float = 3.0
    """Observations reprojecting farther than this (pixels) after a round are dropped ..."""
    outlier_sigmas: float = 3.0
    """... or farther than this many times the round's robust residual sigma (its median
    reprojection error / sqrt(2 ln 2), the 2-D Gaussian's), whichever is less (0: the fixed
    ``outlier_px`` alone). The sigma follows the cameras' noise: tracks on clean synthetic
    images end at ~0.2 px, with the ``--camera realistic`` effects ~0.25 px, while
    ``outlier_px`` is 12 such sigmas."""
    keyframe_sigma_max: float = 1.0
    """After the first round, a keyframe whose own reprojection errors are larger than the
    round's (robust sigmas: median / sqrt(2 ln 2)) has its observations' pixel sigma grown by
    the ratio, at most this factor (1: every keyframe weighs ``pixel_sigma_px``). Dark,
    high-gain and blurred frames track worse: on realistic room-aggressive the observations'
    median error against the truth is 0.12 px at 0-4 ms exposures, 0.27 px at 8-11 ms."""
    rounds: int = 2
    """Levenberg-Marquardt solves. After each but the last the round's outliers
    (``outlier_sigmas``) are dropped (and after the first the IMU refitted) before the next;
    each round's limit comes from the errors the rounds before kept, so a third round trims
    the tail the second narrowed. 3 took room-aggressive's adjustment 1-15 % closer to the
    truth, clean more than realistic (BENCHMARKS.md, agg17d); 2 by default."""
    max_iterations: int = 15
    relative_error_tol: float = 1e-3
    """Stop when an iteration lowers the error by less than this share. On the four suite
    sequences' adjustments the keyframes stop moving (keyframe ATE within 0.02 mm of the
    15-iteration result) once an iteration gains under 0.1 %; GTSAM's default (1e-5) ran
    all 15 (BENCHMARKS.md)."""
    time_budget_s: float | None = None
    """Stop iterating before an iteration that would end past this time from the adjustment's
    start (judged by the last iteration's time), keeping the estimate so far (at least one
    iteration; the outlier round is then skipped). None: no limit."""
    min_observations: int = 20
    """Every keyframe needs this many observations of kept landmarks, else there is no
    adjustment (None): a keyframe held only by its odometry edges could be dragged anywhere."""
    max_track_s: float = 4.0
    """Front-end tracks longer than this are split into separate landmarks (KLT tracks drift:
    reprojected from their first stereo triangulation with ground-truth poses, median 0.25 px
    after 0.3-1 s, 0.8 px after 2-4 s, 1.4 px after 8 s, against 0.12 px at first). With only
    the loops' landmarks fused, 1 s scored best; with the fusion search, longer tracks hold
    the passes together better. Keyframe ATE (mm) for spans 1 / 2 / 4 / unsplit s: figure8
    4.8 / 3.6 / 3.1 / 2.9, loop 1.45 / 1.50 / 1.51 / 1.66, aggressive 2.5 for all, hall 9.5 /
    8.7 / 9.4 / 8.6."""
    odometry_sigma_scale: float = 1.0
    """Multiplies the odometry edges' sigmas (0: no odometry edges)."""
    odometry_huber_k: float = 3.0
    """Huber threshold of the odometry edges, in (scaled) standard deviations (0: plain
    Gaussian). Edges from before the back end's initialisation carry its change of frame
    (measured on room-figure8: keyframe 1 -> 2 off by 28 mm) and a reset back end leaves a
    jump: with a quadratic cost such an edge dragged its keyframes 5-7 mm away from what their
    observations said."""
    max_keyframes_per_landmark: int = 0
    """Keep at most about this many of each track's (or fused landmark's: ``thin_by``)
    keyframe observations, evenly spread over the keyframes that saw it, its first and last
    always (0: all); a keyframe left with fewer than twice ``min_observations`` keeps all of
    its own. A landmark tracked
    through 40 keyframes a few centimetres apart adds 40 nearly identical constraints; the
    iteration's cost grows with every one."""
    thin_by: Literal["track", "landmark"] = "track"
    """What ``max_keyframes_per_landmark`` counts over: each front-end ``track`` (a landmark id
    within one ``max_track_s`` span, before fusion: every pass over a place keeps its own
    share) or each fused ``landmark`` (the revisits' few observations then lose out to the
    first pass's many: on the hall's inputs, keyframe ATE after the adjustment 5.17 mm against
    4.61 with no thinning and 4.52 by track; BENCHMARKS.md)."""
    max_observations_per_landmark: int = 40
    """With ``thin_by`` track: a fused landmark's tracks share this many keyframe
    observations (each keeps at most this divided by their number, at least 2 and at most
    ``max_keyframes_per_landmark``; 0: no shared limit). In a small room every pass fuses into
    the same landmarks: on room-aggressive 1,847 landmarks held 125,000 observations, and
    eliminating a landmark seen by a hundred keyframes makes a dense block over all of them
    (the first iteration allocated 0.9 GB and took 5 s in the run)."""
    anchor: str = "weak"
    """Gauge: "weak" priors on every keyframe's initial pose (no single keyframe trusted: the
    first ones may predate the back end's initialisation), or "fixed" (``fixed_id`` held)."""
    anchor_sigma_m: float = 1.0
    anchor_sigma_rad: float = 0.1
    imu_scale_error: float = 0.005
    """With IMU readings (``inertial``): the scale / axis error the IMU factors' noise allows
    for in the first round (``slam.backend.imu.scale_error_params``, as the back end's
    ``imu_gyro_scale_error`` / ``imu_accel_scale_error``)."""
    imu_refit: bool = True
    """After the first round, fit the IMU's correction matrices (scale, misalignment:
    ``slam.backend.imu_intrinsics.fit_intrinsics``) to the round's keyframes over the whole
    run, re-integrate the readings through them and solve the second round with
    ``imu_refit_scale_error``."""
    imu_refit_scale_error: float = 0.001
    imu_refit_interval_s: float = 0.5
    imu_refit_prior_sigma: float = 0.01
    imu_refit_max_std: float = 0.0007
    """A sensor's fitted matrix is used only when the standard deviations of its three scale
    factors are all below this (else that sensor stays as read); the tighter allowance
    ``imu_refit_scale_error`` only when both sensors' are (else ``imu_scale_error`` again).
    Where the motion does not excite an axis the fit is held near the identity by its prior
    and can be wrong by more than the allowance."""
    imu_odometry_edges: bool = False
    """Keep the odometry edge between two keyframes an IMU factor joins (False: the IMU
    factor replaces it; the edge is the smoother's estimate from the same readings)."""
    imu_odometry_rotation_only: bool = False
    """With IMU factors: an odometry edge between two keyframes that no IMU factor joins (the
    back end handed over no state for one of them: a monocular scale check's restart drops the
    states still in the smoother's window) keeps only its relative rotation, its translation
    left free (sigma 1 km). A monocular smoother's relative translations are at its own scale
    of the time, and a few tight edges (2 mm) outweigh the IMU factors' hold on the map's
    scale: on room-figure8 seed 21, 11 such edges at the scale of a wrong start took the whole
    adjusted map to scale 1.129 (keyframe ATE 183 mm; with rotation-only edges 19.6 mm;
    BENCHMARKS.md, mono18i)."""
    imu_midpoint_rotation: bool = False
    """The IMU factors' readings integrated by the midpoint rule (``slam.backend.imu.
    integrate_pieces``' ``midpoint_rotation``): GTSAM's start-of-piece rotation leaves a
    systematic acceleration that a monocular map's weakly held scale follows."""
    imu_bias_sigma_gyro_rad_s: float = 0.01
    imu_bias_sigma_accel_m_s2: float = 0.1
    """Weak priors on every bias state at the back end's estimate (the accelerometer's sigma
    times the accelerometer walk factor where that applies: the back end's estimates came
    from the calibrated walk; with 505 bias states, 0.1 m/s^2 each holds their mean to 4.5
    mm/s^2. On the fair V1_01 renders, x10 took the loop-closed Sim(3) scale error 0.44 /
    0.31 / 0.39 -> 0.40 / 0.24 / 0.34 %, offline; BENCHMARKS.md, v101walk20)."""
    imu_accel_walk_factor: float = 1.0
    """The accelerometer bias's random walk in the IMU factors (and in the refit's bias model):
    the calibration's times this. A real accelerometer's bias can wander further than its
    calibrated random walk allows: EuRoC V1_01's wanders 0.03-0.18 m/s^2 within 10 s where
    3e-3 m/s^3/sqrt(Hz) allows 0.01 (BENCHMARKS.md, v101imu18). Held to the calibrated walk,
    the bias leaves that wander in the IMU factors, and a monocular map's scale, held by them
    alone, takes it up. Looser than the data's, the bias takes up part of a monocular scale
    error instead where the motion is slow and smooth (BENCHMARKS.md, v101mono18)."""
    imu_gyro_walk_factor: float = 1.0
    """The same for the gyro bias's random walk."""
    imu_walk_gate: float = 0.0
    """With it above 0, each of those factors applies only where the back end's estimates of
    that sensor's bias (``inertial``) wandered at least this many times as far as its
    calibrated random walk allows (:func:`bias_wander`); elsewhere the calibrated walk stays.
    0: the factors always apply."""
    imu_accel_bias_smoothing: float = 0.0
    """With it above 0, where ``imu_accel_walk_factor`` applies (behind ``imu_walk_gate``):
    the accelerometer bias is also held by a second-order (integrated) random walk of this
    density (m/s^2 per s^1.5): its change per second from one IMU factor to the next,
    ``(b_c - b_b) / dt_bc - (b_b - b_a) / dt_ab``, has sigma this times
    ``sqrt((dt_ab + dt_bc) / 2)``. Such a bias is free to drift slowly but not to follow the
    motion's accelerations (its spectrum falls as 1/f^4, the walk's as 1/f^2). The IMU factors
    then hold each interval's bias constant (``ImuFactor``, the readings' noise from the
    calibration alone) and the bias states are joined by their own walk factors
    (``BetweenFactorConstantBias``, the walks times the factors): in a ``CombinedImuFactor``
    a loose walk also widens the preintegrated position and velocity noise, and the IMU's
    hold on the map's scale with it (walk x1000 there: V1_01 scene 0's loop-closed scale error
    0.90 %; BENCHMARKS.md, v101walk20). 0: none."""


@dataclass(frozen=True, eq=False)
class GlobalBaResult:
    world_from_body: dict[int, np.ndarray]
    keyframes: int
    landmarks: int
    fused_landmarks: int
    observations: int
    outliers: int
    rms_px_before: float
    rms_px_after: float
    iterations: int
    seconds: float
    fusion_keyframe_pairs: int = 0
    """Keyframe pairs of different passes matched to find more landmarks to fuse (the
    caller's fusion search; 0 without one)."""
    fusion_seconds: float = 0.0
    fusion_keyframes_searched: int = 0
    """Keyframes the fusion search visited before its share of the time budget ran out."""
    time_boxed: bool = False
    """The time budget stopped the iterations before convergence."""
    outlier_limit_px: float = 0.0
    """The first round's outlier threshold (``GlobalBaParams.outlier_sigmas``)."""
    imu_factors: int = 0
    """Keyframe intervals joined by an IMU factor (0: no IMU readings given)."""
    imu_intrinsics: ImuIntrinsics | None = None
    """The IMU correction matrices used in the second round (``imu_refit``; a sensor whose
    fit was not certain enough stays the identity), or None."""
    imu_scale_std: tuple[float, float] = (0.0, 0.0)
    imu_bias_wander: tuple[float, float] | None = None
    """(accelerometer, gyro) :func:`bias_wander` of the input, when ``imu_walk_gate`` asked."""
    imu_walk_factors: tuple[float, float] = (1.0, 1.0)
    """(accelerometer, gyro) random-walk factors the IMU factors used."""
    """The fit's largest scale-factor standard deviation, gyro and accelerometer."""

    def summary(self) -> dict[str, float | int]:
        return {
            "keyframes": self.keyframes,
            "landmarks": self.landmarks,
            "fused_landmarks": self.fused_landmarks,
            "observations": self.observations,
            "outliers": self.outliers,
            "rms_px_before": round(self.rms_px_before, 4),
            "rms_px_after": round(self.rms_px_after, 4),
            "iterations": self.iterations,
            "seconds": round(self.seconds, 3),
            "fusion_keyframe_pairs": self.fusion_keyframe_pairs,
            "fusion_seconds": round(self.fusion_seconds, 3),
            "fusion_keyframes_searched": self.fusion_keyframes_searched,
            "time_boxed": self.time_boxed,
            "outlier_limit_px": round(self.outlier_limit_px, 4),
        } | self._imu_summary()

    def _imu_summary(self) -> dict[str, float | int]:
        if not self.imu_factors:
            return {}
        out: dict[str, float | int] = {"imu_factors": self.imu_factors}
        if self.imu_intrinsics is not None:
            for name, m in (
                ("gyro", self.imu_intrinsics.gyro_matrix),
                ("accel", self.imu_intrinsics.accel_matrix),
            ):
                for axis, v in zip("xyz", np.diag(m).tolist(), strict=True):
                    out[f"imu_{name}_scale_{axis}"] = round(float(v), 6)
            out["imu_gyro_scale_std"] = round(self.imu_scale_std[0], 6)
            out["imu_accel_scale_std"] = round(self.imu_scale_std[1], 6)
        if self.imu_bias_wander is not None:
            out["imu_accel_bias_wander"] = round(self.imu_bias_wander[0], 4)
            out["imu_gyro_bias_wander"] = round(self.imu_bias_wander[1], 4)
        if self.imu_bias_wander is not None or self.imu_walk_factors != (1.0, 1.0):
            out["imu_accel_walk_factor"] = self.imu_walk_factors[0]
            out["imu_gyro_walk_factor"] = self.imu_walk_factors[1]
        return out


def _fuse(ids: np.ndarray, pairs: Iterable[tuple[int, int]]) -> np.ndarray:
    """Representative landmark id of each of ``ids`` after merging ``pairs`` (union-find)."""
    parent: dict[int, int] = {}

    def find(a: int) -> int:
        root = a
        while parent.get(root, root) != root:
            root = parent[root]
        while parent.get(a, a) != root:  # path compression
            parent[a], a = root, parent[a]
        return root

    for a, b in pairs:
        ra, rb = find(int(a)), find(int(b))
        if ra != rb:
            parent[max(ra, rb)] = min(ra, rb)
    if not parent:
        return ids
    unique, inverse = np.unique(ids, return_inverse=True)  # one find per id, not per row
    roots = np.array([find(int(i)) for i in unique.tolist()], dtype=np.int64)
    return roots[inverse.reshape(-1)]


def _project(
    cam_from_world: np.ndarray, k: np.ndarray, points_w: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """(pixels (N, 2), depth (N,)) of world points through per-row 4x4 cam_from_world."""
    p = np.einsum("nij,nj->ni", cam_from_world[:, :3, :3], points_w) + cam_from_world[:, :3, 3]
    z = p[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        uv = p[:, :2] / z[:, None] * [k[0, 0], k[1, 1]] + [k[0, 2], k[1, 2]]
    return uv, z


def _spread_rows(group: np.ndarray, t: np.ndarray, at_most: int | np.ndarray) -> np.ndarray:
    """Row indices that keep about ``at_most`` rows of each ``group`` (its first and last in
    ``t`` order, the others evenly spread between), in their original order. ``at_most``: one
    limit, or each row's group's limit."""
    order = np.lexsort((t, group))
    if isinstance(at_most, np.ndarray):
        at_most = at_most[order]
    g = group[order]
    start = np.r_[0, np.flatnonzero(g[1:] != g[:-1]) + 1]
    size = np.diff(np.r_[start, len(g)])
    rank = np.arange(len(g)) - np.repeat(start, size)
    count = np.repeat(size, size)
    step = np.maximum(count - 1, 1) / np.maximum(at_most - 1, 1)
    slot = np.floor(rank / step)
    prev_slot = np.floor((rank - 1) / step)
    keep = (count <= at_most) | (rank == 0) | (rank == count - 1) | (slot != prev_slot)
    return np.sort(order[keep])


def _thinned(
    group: np.ndarray,
    t: np.ndarray,
    kf_of: np.ndarray,
    at_most: int | np.ndarray,
    min_observations: int,
) -> np.ndarray:
    """Mask of the observation rows kept when each ``group`` (a track or a fused landmark)
    keeps about ``at_most`` of its rows (``_spread_rows``); a keyframe the thinning would
    leave with fewer than ``2 * min_observations`` keeps all of its own."""
    thin = np.zeros(len(group), bool)
    thin[_spread_rows(group, t, at_most)] = True
    kfs, counts = np.unique(kf_of[thin], return_counts=True)
    thin |= ~np.isin(kf_of, kfs[counts >= 2 * min_observations])
    return thin


def global_bundle_adjustment(
    calib: Calibration,
    observations: dict[int, KeyframeObservations],
    world_from_body: dict[int, np.ndarray],
    odometry_edges: Sequence[PoseEdge],
    fused_pairs: Iterable[tuple[int, int, int, int]],
    fixed_id: int,
    keyframe_t_ns: dict[int, int],
    params: GlobalBaParams | None = None,
    inertial: Mapping[int, KeyframeInertial] | None = None,
    imu: ImuCalibration | None = None,
) -> GlobalBaResult | None:
    """Re-estimate the keyframes in ``world_from_body`` (initial guesses, e.g. after PGO) with
    every observation in ``observations``. ``fused_pairs``: (keyframe a, landmark a, keyframe b,
    landmark b) that a loop matched (the landmark of one keyframe is the other's);
    ``keyframe_t_ns``: keyframe times (for ``max_track_s``). None when some keyframe has
    fewer than ``min_observations`` usable observations.

    ``inertial`` (with the IMU's calibration ``imu``): per keyframe its velocity and biases
    (initial values; velocity in the frame of ``world_from_body``, z up) and the IMU readings
    from the keyframe before it: consecutive keyframes both adjusted are joined by a
    ``CombinedImuFactor`` (visual-inertial full adjustment, as ORB-SLAM3's), which replaces
    their odometry edge (``imu_odometry_edges``)."""
    p = params or GlobalBaParams()
    t0 = time.perf_counter()
    accel_factor, gyro_factor = p.imu_accel_walk_factor, p.imu_gyro_walk_factor
    wander = None
    if imu is not None and inertial and p.imu_walk_gate > 0:
        wander = bias_wander(inertial, imu)
        if wander is None or wander[0] < p.imu_walk_gate:
            accel_factor = 1.0
        if wander is None or wander[1] < p.imu_walk_gate:
            gyro_factor = 1.0
    between = p.imu_accel_bias_smoothing > 0 and accel_factor != 1.0
    # ``imu`` stays as calibrated; ``imu_walked`` has the walk factors applied. The bias walk
    # goes into the IMU factors themselves, or, with ``between``, into separate bias factors
    # (and then the IMU factors keep the calibrated walk).
    imu_walked = imu
    if imu is not None and (accel_factor != 1.0 or gyro_factor != 1.0):
        imu_walked = dataclasses.replace(
            imu,
            accel_random_walk=imu.accel_random_walk * accel_factor,
            gyro_random_walk=imu.gyro_random_walk * gyro_factor,
        )
    imu_of_factors = imu if between else imu_walked
    kf_ids = sorted(k for k in world_from_body if k in observations)
    cams = calib.cameras[:2]
    body_from_cam = [np.asarray(c.body_from_cam, dtype=float) for c in cams]
    k_mats = [np.asarray(c.intrinsics.K, dtype=float) for c in cams]
    pairs = [(int(a), int(b), int(c), int(d)) for a, b, c, d in fused_pairs]

    # Flatten the observations: one row per (keyframe, landmark).
    rows_kf, rows_lid, rows_l, rows_r, rows_p = [], [], [], [], []
    for k in kf_ids:
        o = observations[k]
        n = len(o.landmark_ids)
        rows_kf.append(np.full(n, k, dtype=np.int64))
        rows_lid.append(np.asarray(o.landmark_ids, dtype=np.int64))
        rows_l.append(np.asarray(o.left_px, dtype=float).reshape(n, 2))
        rows_r.append(np.asarray(o.right_px, dtype=float).reshape(n, 2))
        rows_p.append(np.asarray(o.points_cam0, dtype=float).reshape(n, 3))
    kf_of = np.concatenate(rows_kf) if rows_kf else np.zeros(0, np.int64)
    raw_lid = np.concatenate(rows_lid) if rows_lid else np.zeros(0, np.int64)
    # Split long tracks: landmark id -> (id, age bucket) -> a new dense id.
    t_row = np.array([keyframe_t_ns[int(k)] for k in kf_of], dtype=np.int64)
    uniq_raw, inv_raw = np.unique(raw_lid, return_inverse=True)
    t_first = np.full(len(uniq_raw), np.iinfo(np.int64).max)
    np.minimum.at(t_first, inv_raw, t_row)
    span_ns = max(int(p.max_track_s * 1e9), 1)
    bucket = (t_row - t_first[inv_raw]) // span_ns
    seg_keys = np.stack([inv_raw, bucket], axis=1)
    _, split_id = np.unique(seg_keys, axis=0, return_inverse=True)
    split_id = split_id.reshape(-1).astype(np.int64)
    row_of = {(int(k), int(i)): r for r, (k, i) in enumerate(zip(kf_of.tolist(), raw_lid.tolist()))}
    split_pairs = [
        (int(split_id[row_of[(ka, la)]]), int(split_id[row_of[(kb, lb)]]))
        for ka, la, kb, lb in pairs
        if (ka, la) in row_of and (kb, lb) in row_of
    ]
    lid = _fuse(split_id, split_pairs)
    fused_of = dict(zip(split_id.tolist(), lid.tolist(), strict=True))
    fused = len({fused_of[a] for a, _ in split_pairs})  # fused landmarks the pairs made
    left = np.concatenate(rows_l) if rows_l else np.zeros((0, 2))
    right = np.concatenate(rows_r) if rows_r else np.zeros((0, 2))
    pts_cam = np.concatenate(rows_p) if rows_p else np.zeros((0, 3))
    # One observation per (keyframe, fused landmark).
    _, first = np.unique(np.stack([kf_of, lid], axis=1), axis=0, return_index=True)
    keep = np.sort(first)
    kf_of, lid, left, right, pts_cam = (
        kf_of[keep],
        lid[keep],
        left[keep],
        right[keep],
        pts_cam[keep],
    )
    if p.max_keyframes_per_landmark > 0:
        track = split_id[keep]
        group = lid if p.thin_by == "landmark" else track
        at_most: int | np.ndarray = p.max_keyframes_per_landmark
        if p.thin_by == "track" and p.max_observations_per_landmark > 0:
            # Each fused landmark's tracks share its limit: at least 2 each.
            lm_of_track = np.unique(np.stack([lid, track], axis=1), axis=0)[:, 0]
            lms, tracks_per_lm = np.unique(lm_of_track, return_counts=True)
            share = p.max_observations_per_landmark // tracks_per_lm[np.searchsorted(lms, lid)]
            at_most = np.clip(share, 2, p.max_keyframes_per_landmark)
        thin = _thinned(group, t_row[keep], kf_of, at_most, p.min_observations)
        kf_of, lid = kf_of[thin], lid[thin]
        left, right, pts_cam = left[thin], right[thin], pts_cam[thin]
    # Landmarks in enough keyframes, each with an initial guess from its first usable keyframe.
    uniq, inverse, counts = np.unique(lid, return_inverse=True, return_counts=True)
    depth = pts_cam[:, 2]
    usable = np.all(np.isfinite(pts_cam), axis=1) & (depth > 0.05) & (depth < p.max_depth_m)
    guess = np.full((len(uniq), 3), np.nan)
    order = np.flatnonzero(usable)[::-1]  # the last write wins: the first usable observation
    poses = np.array([world_from_body[int(k)] for k in kf_of]).reshape(-1, 4, 4)
    world_from_cam0 = poses @ body_from_cam[0]
    pts_w = np.einsum("nij,nj->ni", world_from_cam0[:, :3, :3], pts_cam) + world_from_cam0[:, :3, 3]
    guess[inverse[order]] = pts_w[order]
    good_lm = (counts >= p.min_keyframes) & np.all(np.isfinite(guess), axis=1)
    obs = good_lm[inverse]
    per_kf = dict(zip(*np.unique(kf_of[obs], return_counts=True), strict=True))
    if not kf_ids or min(int(per_kf.get(k, 0)) for k in kf_ids) < p.min_observations:
        return None

    graph = gtsam.NonlinearFactorGraph()
    values = gtsam.Values()
    for k in kf_ids:
        values.insert(_pose_key(k), gtsam.Pose3(np.asarray(world_from_body[k], dtype=float)))
    for i in np.flatnonzero(good_lm).tolist():
        values.insert(_point_key(i), guess[i])
    if p.anchor == "fixed":
        graph.add(
            gtsam.PriorFactorPose3(
                _pose_key(fixed_id),
                gtsam.Pose3(np.asarray(world_from_body[fixed_id], dtype=float)),
                gtsam.noiseModel.Isotropic.Sigma(6, 1e-6),
            )
        )
    else:
        weak = gtsam.noiseModel.Diagonal.Sigmas(
            np.array([p.anchor_sigma_rad] * 3 + [p.anchor_sigma_m] * 3)
        )
        for k in kf_ids:
            graph.add(
                gtsam.PriorFactorPose3(
                    _pose_key(k), gtsam.Pose3(np.asarray(world_from_body[k], dtype=float)), weak
                )
            )
    kf_set = set(kf_ids)
    links = _imu_links(kf_ids, inertial) if inertial is not None and imu is not None else []
    linked = set(links)
    if p.odometry_sigma_scale > 0:
        for e in odometry_edges:
            if (e.from_id, e.to_id) in linked and not p.imu_odometry_edges:
                continue
            if e.from_id in kf_set and e.to_id in kf_set:
                info = e.information / p.odometry_sigma_scale**2
                if p.imu_odometry_rotation_only and links and (e.from_id, e.to_id) not in linked:
                    info = _rotation_only(info)
                noise: gtsam.noiseModel.Base = gaussian_from_g2o_information(info)
                if p.odometry_huber_k > 0:
                    noise = gtsam.noiseModel.Robust.Create(
                        gtsam.noiseModel.mEstimator.Huber.Create(p.odometry_huber_k), noise
                    )
                graph.add(
                    gtsam.BetweenFactorPose3(
                        _pose_key(e.from_id),
                        _pose_key(e.to_id),
                        gtsam.Pose3(np.asarray(e.from_node_from_to_node, dtype=float)),
                        noise,
                    )
                )
    imu_keyframes = sorted({k for link in links for k in link})
    if links:
        assert inertial is not None and imu is not None
        # A looser accelerometer walk (behind the gate) loosens the prior on the back end's
        # estimates by the same factor: they came from the calibrated walk.
        bias_prior = gtsam.noiseModel.Diagonal.Sigmas(
            np.array(
                [p.imu_bias_sigma_accel_m_s2 * accel_factor] * 3 + [p.imu_bias_sigma_gyro_rad_s] * 3
            )
        )
        for k in imu_keyframes:
            st = inertial[k]
            bias = make_bias(st.bias_gyro_rad_s, st.bias_accel_m_s2)
            values.insert(_velocity_key(k), np.asarray(st.velocity_world_m_s, dtype=float))
            values.insert(_bias_key(k), bias)
            graph.add(gtsam.PriorFactorConstantBias(_bias_key(k), bias, bias_prior))
        if between:
            assert imu_walked is not None
            _add_bias_walks(graph, values, links, inertial, imu_walked, p.imu_accel_bias_smoothing)
    cal = [
        gtsam.Cal3_S2(c.intrinsics.fx, c.intrinsics.fy, 0.0, c.intrinsics.cx, c.intrinsics.cy)
        for c in cams
    ]
    body_p_cam = [gtsam.Pose3(m) for m in body_from_cam]

    def pixel_noise(sigma_px: float) -> gtsam.noiseModel.Base:
        """An observation's noise: isotropic ``sigma_px`` behind the Huber kernel."""
        return gtsam.noiseModel.Robust.Create(
            gtsam.noiseModel.mEstimator.Huber.Create(p.huber_k),
            gtsam.noiseModel.Isotropic.Sigma(2, sigma_px),
        )

    noise_px = pixel_noise(p.pixel_sigma_px)
    has_right = np.all(np.isfinite(right), axis=1) & (len(cams) > 1)
    kf_index = np.searchsorted(np.asarray(kf_ids), kf_of)  # row -> position in kf_ids
    pose_key_of_row = np.array([_pose_key(k) for k in kf_ids], dtype=np.uint64)[kf_index].tolist()
    point_key_of_row = _point_keys(inverse)
    # Each good landmark's row in gtsam.utilities.extractPoint3 (Values sorted by key).
    point_slot = np.cumsum(good_lm) - 1

    def add_projections(
        g: gtsam.NonlinearFactorGraph,
        rows: np.ndarray,
        cam: int,
        noise_of_row: dict[int, gtsam.noiseModel.Base] | None = None,
    ) -> np.ndarray:
        """Add a projection factor for each row in ``cam`` (``noise_of_row``: rows whose
        noise is not ``noise_px``); their factor indices in ``g``."""
        first = int(g.size())
        px = left if cam == 0 else right
        for r in rows.tolist():
            g.add(
                gtsam.GenericProjectionFactorCal3_S2(
                    px[r],
                    noise_px if noise_of_row is None else noise_of_row.get(r, noise_px),
                    pose_key_of_row[r],
                    point_key_of_row[r],
                    cal[cam],
                    body_p_cam[cam],
                )
            )
        return first + np.arange(len(rows))

    def errors(
        vals: gtsam.Values, mask_l: np.ndarray, mask_r: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """Reprojection error (px) of every row in each camera (inf where masked out)."""
        body_w = np.array([vals.atPose3(_pose_key(int(k))).matrix() for k in kf_ids])
        kept = gtsam.utilities.extractPoint3(vals)
        pts = kept[point_slot[inverse]] if len(kept) else np.full((len(lid), 3), np.nan)
        out = []
        for cam, mask, px in ((0, mask_l, left), (1, mask_r, right)):
            if cam >= len(body_from_cam):  # monocular: no right camera
                out.append(np.full(len(px), np.inf))
                continue
            cam_from_world = np.linalg.inv(body_w @ body_from_cam[cam])[kf_index]
            uv, z = _project(cam_from_world, k_mats[cam], pts)
            err = np.linalg.norm(uv - px, axis=1)
            err[~mask | ~(z > 0) | ~np.isfinite(err)] = np.inf
            out.append(err)
        return out[0], out[1]

    mask_l, mask_r = obs.copy(), obs & has_right
    e_l, e_r = errors(values, mask_l, mask_r)
    finite = np.concatenate([e_l[np.isfinite(e_l)], e_r[np.isfinite(e_r)]])
    rms_before = float(np.sqrt(np.mean(finite**2))) if len(finite) else 0.0
    lm_params = gtsam.LevenbergMarquardtParams()
    lm_params.setMaxIterations(p.max_iterations)
    lm_params.setRelativeErrorTol(p.relative_error_tol)
    iterations = 0
    result = values
    deadline = None if p.time_budget_s is None else t0 + p.time_budget_s
    time_boxed = False
    iteration_s: float | None = None
    outlier_limit: float | None = None
    # One graph for both rounds: the second removes the outliers' factors (GTSAM skips
    # removed ones) instead of building the graph again in Python (1.3 s on the hall).
    full = gtsam.NonlinearFactorGraph(graph)
    factor_l = np.full(len(lid), -1)
    factor_r = np.full(len(lid), -1)
    factor_l[mask_l] = add_projections(full, np.flatnonzero(mask_l), 0)
    factor_r[mask_r] = add_projections(full, np.flatnonzero(mask_r), 1)
    factor_imu = np.zeros(0, dtype=np.int64)
    fitted: ImuIntrinsics | None = None
    scale_std = (0.0, 0.0)
    if links:
        assert inertial is not None and imu_of_factors is not None
        imu_first = int(full.size())
        for a, b in links:
            full.add(
                _imu_factor(
                    a, b, inertial, values, imu_of_factors, p.imu_scale_error, None, p, between
                )
            )
        factor_imu = imu_first + np.arange(len(links))
    for round_ in range(max(p.rounds, 1)):  # solve; drop outliers; solve again (and again)
        if deadline is not None and iteration_s is not None:
            if time.perf_counter() + iteration_s > deadline:
                time_boxed = True  # no time for the second round's iterations
                break
        optimizer = gtsam.LevenbergMarquardtOptimizer(full, result, lm_params)
        if deadline is None:
            result = optimizer.optimize()
            iterations += int(optimizer.iterations())
        else:
            time_boxed, iteration_s = _iterate_until(optimizer, lm_params, deadline, iteration_s)
            result = optimizer.values()
            iterations += int(optimizer.iterations())
        e_l, e_r = errors(result, mask_l, mask_r)
        limit = _outlier_limit(e_l, e_r, p)
        outlier_limit = limit if outlier_limit is None else outlier_limit
        dropped = np.r_[factor_l[mask_l & ~(e_l < limit)], factor_r[mask_r & ~(e_r < limit)]]
        mask_l &= e_l < limit
        mask_r &= e_r < limit
        reweigh = (
            _keyframe_sigma_factors(e_l, e_r, kf_index, len(kf_ids), p)
            if round_ == 0 and p.keyframe_sigma_max > 1.0
            else None
        )
        refit = None
        if round_ == 0 and p.rounds > 1 and links and p.imu_refit and not time_boxed:
            assert inertial is not None and imu_of_factors is not None
            found = _fit_imu_intrinsics(kf_ids, links, inertial, result, imu_of_factors, p)
            if found is not None:
                refit, scale_std = found
        if time_boxed or (not len(dropped) and reweigh is None and refit is None):
            break
        for i in dropped.tolist():
            full.remove(i)
        if refit is not None:
            assert inertial is not None and imu_of_factors is not None
            fitted = refit
            certain = max(scale_std) < p.imu_refit_max_std
            refit_error = p.imu_refit_scale_error if certain else p.imu_scale_error
            for i in factor_imu.tolist():
                full.remove(i)
            imu_first = int(full.size())
            for a, b in links:
                full.add(
                    _imu_factor(
                        a, b, inertial, result, imu_of_factors, refit_error, refit, p, between
                    )
                )
            factor_imu = imu_first + np.arange(len(links))
        if reweigh is not None:
            # The kept observations of keyframes noisier than the round's: their factors again,
            # with the grown sigma.
            noise_of = {
                f: pixel_noise(p.pixel_sigma_px * f)
                for f in np.unique(reweigh[reweigh > 1.0]).tolist()
            }
            rows_of: dict[int, gtsam.noiseModel.Base] = {
                r: noise_of[float(reweigh[kf_index[r]])]
                for r in np.flatnonzero(reweigh[kf_index] > 1.0).tolist()
            }
            for factors, mask, cam in ((factor_l, mask_l, 0), (factor_r, mask_r, 1)):
                redo = np.flatnonzero(mask & (reweigh[kf_index] > 1.0))
                for i in factors[redo].tolist():
                    full.remove(i)
                factors[redo] = add_projections(full, redo, cam, rows_of)
    e_l, e_r = errors(result, mask_l, mask_r)
    finite = np.concatenate([e_l[np.isfinite(e_l)], e_r[np.isfinite(e_r)]])
    rms_after = float(np.sqrt(np.mean(finite**2))) if len(finite) else 0.0
    return GlobalBaResult(
        world_from_body={k: result.atPose3(_pose_key(k)).matrix() for k in kf_ids},
        keyframes=len(kf_ids),
        landmarks=int(good_lm.sum()),
        fused_landmarks=fused,
        observations=int(obs.sum() + (obs & has_right).sum()),
        outliers=int((obs & ~mask_l).sum() + (obs & has_right & ~mask_r).sum()),
        rms_px_before=rms_before,
        rms_px_after=rms_after,
        iterations=iterations,
        seconds=time.perf_counter() - t0,
        time_boxed=time_boxed,
        outlier_limit_px=p.outlier_px if outlier_limit is None else outlier_limit,
        imu_factors=len(links),
        imu_intrinsics=fitted,
        imu_scale_std=scale_std,
        imu_bias_wander=wander,
        imu_walk_factors=(accel_factor, gyro_factor),
    )


BIAS_WANDER_LAG_S = 10.0
"""The time over which :func:`bias_wander` compares bias estimates: long enough for the back
end's smoothing of its estimates (its window, 2-3 s) to matter little."""


def bias_wander(
    inertial: Mapping[int, KeyframeInertial],
    imu: ImuCalibration,
    lag_s: float = BIAS_WANDER_LAG_S,
) -> tuple[float, float] | None:
    """How far the back end's bias estimates wandered, against the calibrated random walks:
    (accelerometer, gyro), each the median over keyframes at t of |b(t') - b(t)|^2 /
    (3 q^2 (t' - t)), t' the first keyframe at least ``lag_s`` later and q the walk's density.
    A bias that follows its calibrated walk gives about 0.8 (the median of a chi-square with
    3 degrees of freedom, over 3); the back end's estimates, smoothed by that walk's model,
    give less where the data agrees with it (the suite's renders: 0.5-1.2). An IMU whose bias
    wanders further gives more (the real V1_01 IMU's on the fair renders: 2.1 and 2.7-3.1).
    The median: a back end's restart (its biases start over) makes a few large steps. None
    without a keyframe ``lag_s`` after another."""
    ks = sorted(inertial)
    t_s = np.array([inertial[k].t_ns for k in ks], dtype=np.int64) * 1e-9
    later = np.searchsorted(t_s, t_s + lag_s)
    ok = later < len(ks)
    if not ok.any():
        return None
    dt = t_s[later[ok]] - t_s[ok]
    out = []
    for q, bias in (
        (imu.accel_random_walk, np.array([inertial[k].bias_accel_m_s2 for k in ks])),
        (imu.gyro_random_walk, np.array([inertial[k].bias_gyro_rad_s for k in ks])),
    ):
        step2 = np.sum((bias[later[ok]] - bias[ok]) ** 2, axis=1)
        out.append(float(np.median(step2 / (3.0 * q**2 * dt))))
    return out[0], out[1]


def _rotation_only(info_g2o: np.ndarray) -> np.ndarray:
    """A 6x6 g2o-order information matrix (translation first) with its translation rows and
    columns replaced by a 1 km sigma: the edge then holds the relative rotation alone."""
    out = np.array(info_g2o, dtype=float)
    out[:3, :] = 0.0
    out[:, :3] = 0.0
    out[:3, :3] = np.eye(3) * 1e-6
    return out


def _add_bias_walks(
    graph: gtsam.NonlinearFactorGraph,
    values: gtsam.Values,
    links: Sequence[tuple[int, int]],
    inertial: Mapping[int, KeyframeInertial],
    imu: ImuCalibration,
    smoothing: float,
) -> None:
    """``GlobalBaParams.imu_accel_bias_smoothing``'s bias factors: a random walk (``imu``'s,
    the walk factors applied) between the bias states of each IMU factor's keyframes, and the
    accelerometer's second-order walk of density ``smoothing`` on every chain of two, (a, b),
    (b, c); the latter linear in the biases, so one ``LinearContainerFactor`` each, at
    ``values``."""
    walk = np.array([imu.accel_random_walk] * 3 + [imu.gyro_random_walk] * 3)
    dt_of = {(a, b): (inertial[b].t_ns - inertial[a].t_ns) * 1e-9 for a, b in links}
    for (a, b), dt in dt_of.items():
        graph.add(
            gtsam.BetweenFactorConstantBias(
                _bias_key(a),
                _bias_key(b),
                gtsam.imuBias.ConstantBias(),
                gtsam.noiseModel.Diagonal.Sigmas(walk * np.sqrt(max(dt, 1e-3))),
            )
        )
    next_of = dict(links)
    pick = np.eye(6)[:3]  # a ConstantBias's tangent vector: accelerometer first
    for a, b in links:
        c = next_of.get(b)
        if c is None:
            continue
        dt_ab, dt_bc = dt_of[(a, b)], dt_of[(b, c)]
        if dt_ab <= 0 or dt_bc <= 0:
            continue
        coef = (1.0 / dt_ab, -(1.0 / dt_ab + 1.0 / dt_bc), 1.0 / dt_bc)
        keys = (_bias_key(a), _bias_key(b), _bias_key(c))
        at = gtsam.Values()
        for k in keys:
            at.insert(k, values.atConstantBias(k))
        r0 = sum(w * at.atConstantBias(k).accelerometer() for w, k in zip(coef, keys, strict=True))
        noise = gtsam.noiseModel.Isotropic.Sigma(3, smoothing * np.sqrt(0.5 * (dt_ab + dt_bc)))
        jf = gtsam.JacobianFactor(
            keys[0], coef[0] * pick, keys[1], coef[1] * pick, keys[2], coef[2] * pick, -r0, noise
        )
        graph.add(gtsam.LinearContainerFactor(jf, at))


def _imu_links(
    kf_ids: Sequence[int], inertial: Mapping[int, KeyframeInertial]
) -> list[tuple[int, int]]:
    """(previous keyframe, keyframe) pairs among ``kf_ids`` joined by IMU readings."""
    kf_set = set(kf_ids)
    links = []
    for k in kf_ids:
        st = inertial.get(k)
        if (
            st is None
            or st.previous_keyframe_id not in kf_set
            or st.previous_keyframe_id not in inertial
        ):
            continue
        if len(st.piece_dt_s) and float(np.sum(st.piece_dt_s)) > 0:
            links.append((st.previous_keyframe_id, k))
    return links


def _imu_factor(
    a: int,
    b: int,
    inertial: Mapping[int, KeyframeInertial],
    values: gtsam.Values,
    imu: ImuCalibration,
    scale_error: float,
    intrinsics: ImuIntrinsics | None,
    p: GlobalBaParams,
    between: bool = False,
) -> gtsam.CombinedImuFactor | gtsam.ImuFactor:
    """The IMU factor from keyframe ``a`` to ``b``: ``b``'s readings (through ``intrinsics``
    when given) preintegrated about ``a``'s bias in ``values``, their noise allowing for
    ``scale_error``. ``between``: an ``ImuFactor`` (the bias held over the interval; its
    walk is a factor of its own, ``_add_bias_walks``)."""
    st = inertial[b]
    gyro, accel = st.piece_gyro_rad_s, st.piece_accel_m_s2
    if intrinsics is not None:
        gyro = gyro @ intrinsics.gyro_matrix.T
        accel = accel @ intrinsics.accel_matrix.T
    pieces = (st.piece_dt_s, gyro, accel)
    params = (
        scale_error_params(imu, pieces, scale_error, scale_error)
        if scale_error > 0
        else preintegration_params(imu)
    )
    if between:
        held = gtsam.PreintegratedImuMeasurements(params, values.atConstantBias(_bias_key(a)))
        integrate_pieces(held, pieces, p.imu_midpoint_rotation)
        return gtsam.ImuFactor(
            _pose_key(a), _velocity_key(a), _pose_key(b), _velocity_key(b), _bias_key(a), held
        )
    pim = gtsam.PreintegratedCombinedMeasurements(params, values.atConstantBias(_bias_key(a)))
    integrate_pieces(pim, pieces, p.imu_midpoint_rotation)
    return gtsam.CombinedImuFactor(
        _pose_key(a),
        _velocity_key(a),
        _pose_key(b),
        _velocity_key(b),
        _bias_key(a),
        _bias_key(b),
        pim,
    )


def _fit_imu_intrinsics(
    kf_ids: Sequence[int],
    links: Sequence[tuple[int, int]],
    inertial: Mapping[int, KeyframeInertial],
    values: gtsam.Values,
    imu: ImuCalibration,
    p: GlobalBaParams,
) -> tuple[ImuIntrinsics, tuple[float, float]] | None:
    """The IMU's correction matrices fitted to the adjusted keyframes (``values``) and the raw
    readings between them over the whole run (a sensor whose scale factors are less certain
    than ``imu_refit_max_std`` left at the identity), with the fit's largest scale standard
    deviation per sensor (gyro, accelerometer); None when the fit has too few intervals."""
    prev_of = dict((b, a) for a, b in links)
    states: list[KeyframeState] = []
    previous = -1
    for k in sorted(kf_ids, key=lambda k: inertial[k].t_ns if k in inertial else -1):
        if k not in inertial or not values.exists(_velocity_key(k)):
            previous = -1
            continue
        st = inertial[k]
        pose = values.atPose3(_pose_key(k))
        pieces = None
        if prev_of.get(k) == previous and previous >= 0:
            pieces = (st.piece_dt_s, st.piece_gyro_rad_s, st.piece_accel_m_s2)
        states.append(
            KeyframeState(
                st.t_ns,
                pose.rotation().matrix(),
                np.asarray(pose.translation(), dtype=float),
                np.asarray(values.atVector(_velocity_key(k)), dtype=float),
                pieces,
            )
        )
        previous = k
    fit = fit_intrinsics(
        states,
        np.array([0.0, 0.0, -imu.gravity_m_s2]),
        ImuIntrinsics.identity(),
        p.imu_refit_prior_sigma,
        True,
        p.imu_refit_interval_s,
        imu.accel_random_walk,
    )
    if fit is None:
        return None
    std = (float(np.diag(fit.gyro_std).max()), float(np.diag(fit.accel_std).max()))
    return (
        ImuIntrinsics(
            fit.gyro_matrix if std[0] < p.imu_refit_max_std else np.eye(3),
            fit.accel_matrix if std[1] < p.imu_refit_max_std else np.eye(3),
        ),
        std,
    )


def _keyframe_sigma_factors(
    e_l: np.ndarray, e_r: np.ndarray, kf_index: np.ndarray, n_keyframes: int, p: GlobalBaParams
) -> np.ndarray | None:
    """Each keyframe's pixel sigma factor (``GlobalBaParams.keyframe_sigma_max``): its robust
    residual sigma over the round's, clipped to [1, max] and rounded to 0.1 (a few noise
    models); None when no keyframe gets more than 1. ``e_l``, ``e_r``: inf where left out."""
    err = np.r_[e_l, e_r]
    kf = np.r_[kf_index, kf_index]
    ok = np.isfinite(err)
    if not ok.any():
        return None
    overall = float(np.median(err[ok]))
    med = np.full(n_keyframes, overall)
    order = np.argsort(kf[ok], kind="stable")
    kf_sorted, err_sorted = kf[ok][order], err[ok][order]
    starts = np.r_[0, np.flatnonzero(np.diff(kf_sorted)) + 1]
    for a, b in zip(starts.tolist(), np.r_[starts[1:], len(kf_sorted)].tolist(), strict=True):
        med[kf_sorted[a]] = np.median(err_sorted[a:b])
    factor = np.round(np.clip(med / max(overall, 1e-9), 1.0, p.keyframe_sigma_max), 1)
    return factor if (factor > 1.0).any() else None


def _outlier_limit(e_l: np.ndarray, e_r: np.ndarray, p: GlobalBaParams) -> float:
    """The reprojection error (px) past which an observation is an outlier: ``outlier_px``,
    or ``outlier_sigmas`` robust sigmas of the kept observations' errors (``e_l``, ``e_r``:
    inf where left out) when that is less."""
    finite = np.concatenate([e_l[np.isfinite(e_l)], e_r[np.isfinite(e_r)]])
    if p.outlier_sigmas <= 0 or not len(finite):
        return p.outlier_px
    sigma = float(np.median(finite)) / np.sqrt(2.0 * np.log(2.0))
    return float(min(p.outlier_px, p.outlier_sigmas * sigma))


def _iterate_until(
    optimizer: gtsam.LevenbergMarquardtOptimizer,
    params: gtsam.LevenbergMarquardtParams,
    deadline: float,
    iteration_s: float | None = None,
) -> tuple[bool, float | None]:
    """Levenberg-Marquardt iterations until convergence (GTSAM's own test), the iteration
    limit or ``deadline`` (``time.perf_counter``). An iteration is not started when the last
    one (``iteration_s`` before the first: an earlier round's) would end past the deadline:
    one iteration of room-aggressive's adjustment takes 1-2 s, which a check after each
    iteration added to the end of the run. Without an estimate at least one iteration runs.
    Returns (True when the deadline stopped it, the last iteration's time)."""
    error = optimizer.error()
    for _ in range(params.getMaxIterations()):
        start = time.perf_counter()
        if iteration_s is not None and start + iteration_s > deadline:
            return True, iteration_s
        optimizer.iterate()
        iteration_s = time.perf_counter() - start
        new_error = optimizer.error()
        if gtsam.checkConvergence(
            params.getRelativeErrorTol(),
            params.getAbsoluteErrorTol(),
            params.getErrorTol(),
            error,
            new_error,
        ):
            return False, iteration_s
        error = new_error
    return False, iteration_s


__all__ = [
    "GlobalBaParams",
    "GlobalBaResult",
    "KeyframeObservations",
    "global_bundle_adjustment",
]

"""Visual-inertial alignment of a monocular start: metric scale, gravity, velocities, gyro bias.

The monocular front end's keyframe poses (``Keyframe.world_from_body_vo``) come from two-view
structure from motion and PnP: right up to an unknown scale ``s`` (its first baseline was a
guess) and an unknown orientation of gravity. VINS-Mono's linear alignment (Qin et al., 2018,
section V-B) recovers them from the IMU preintegrated between the keyframes (GTSAM's
``PreintegratedCombinedMeasurements``, through :mod:`slam.backend.imu`):

1. gyro bias: the relative rotations of consecutive keyframes against the preintegrated ones
   (:func:`slam.backend.init.estimate_gyro_bias`, shared with the stereo moving start);
2. velocities ``v_k`` (VO frame, metric), gravity ``g`` (VO frame) and ``s`` by linear least
   squares. The VO positions are of the *body*, computed by the front end from camera centres
   at VO scale with the metric camera-IMU lever arm ``t_bc``; the camera centres
   ``c_k = p_k + R_k t_bc`` are what scales, so the metric body position is
   ``s c_k - R_k t_bc``. Per interval i -> j (``dt``, preintegrated ``dp``, ``dv``):

       s (c_j - c_i) - v_i dt - 1/2 g dt^2 = R_i dp(ba) + (R_j - R_i) t_bc
       v_j - v_i - g dt                    = R_i dv(ba)

   plus an accelerometer bias ``ba`` held near zero by a prior (``dp``, ``dv`` corrected to
   first order with GTSAM's bias Jacobians; VINS-Mono leaves it out, but on slow motion a
   0.07 m/s^2 bias is a quarter of the acceleration that fixes the scale);
3. gravity refined on its sphere (``|g|`` known): a 2-DoF tangent update re-solved a few times
   with ``s``, the velocities and ``ba``.

Before the alignment the keyframe poses are refined by a small bundle adjustment
(:func:`refine_vo_poses`: GTSAM Levenberg-Marquardt over the keyframes' observations, the
first pose held, Huber projection factors): tracked frame to frame by PnP, a monocular map's
scale drifts by a few per cent per second, which the alignment would read as acceleration.

Checks that reject an alignment (the caller waits for more keyframes and tries again): a
non-positive scale, ``|g|`` of the free solution far from the known one, a scale whose
standard deviation (residual variance times ``(A^T A)^-1``) is above ``max_scale_std`` of
it, and a scale that the first two thirds of the keyframes alone do not reproduce. Smooth
motion is the usual failure: on the synthetic figure-8's first 1.5 s even ground-truth poses
align to a scale 1-7 % off, and a VO within 0.3 mm of the truth to one 13 % off.

On gentle motion with a real IMU the bias matters and its prior hides it: held at 0, the
fit's scale moves by the bias's share of the acceleration and its std grows (V1_01: 3-6 % for
19 s) or, worse, stays small (a simulated take-off: accepted 5 % off). ``align_mono``'s retry
also solves with the bias nearly free, whose std is the honest one, and lets that fit decide
where the two scales disagree.

After an accepted alignment, :func:`batch_start` (VINS-Mono's first sliding-window
optimisation over the aligned window) can refine it: one visual-inertial bundle adjustment over
every keyframe of the window (metric poses, velocities and biases; the landmarks' projections,
IMU factors between consecutive keyframes) whose newest state, with the joint marginal
covariance of its pose, velocity and bias, starts the fixed-lag smoother: the window's
evidence for the scale is carried on instead of a loose prior on the newest state alone.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any

import gtsam
import numpy as np

from slam.backend.config import BackendConfig
from slam.backend.imu import (
    bias_noise,
    integrate_pieces,
    integration_pieces,
    make_bias,
    pose_noise,
    preintegration_params,
)
from slam.backend.init import bias_corrected_deltas, estimate_gyro_bias
from slam.core.calibration import ImuCalibration


@dataclass(frozen=True, eq=False)
class MonoAlignment:
    """The result of :func:`align_mono`; ``accepted`` False with a ``reason`` when a check failed."""

    accepted: bool
    reason: str
    scale: float
    """Metric metres per VO unit (camera centres scale by it)."""
    gravity_vo_m_s2: np.ndarray
    """(3,) gravity (pointing down, magnitude |g|) in the VO frame."""
    velocities_vo_m_s: np.ndarray
    """(K, 3) metric body velocity of each keyframe, VO frame orientation."""
    bias_gyro_rad_s: np.ndarray
    bias_accel_m_s2: np.ndarray
    """(3,) held near 0 by a prior (motion over a second or two hardly separates it from
    gravity and the scale; on gentle motion it must be let go: ``accel_bias_sigma_m_s2``);
    the smoother refines it."""
    gravity_norm_free_m_s2: float
    """|g| of the unconstrained linear solution (a health check)."""
    scale_subset: float
    """The scale from the first two thirds of the keyframes alone (a consistency check)."""
    scale_std: float
    """The scale's standard deviation from the fit's residuals (its excitation check)."""
    accel_bias_sigma_m_s2: float
    """The accelerometer-bias prior of this solution (the retry's when that was accepted)."""


def start_gate(n_keyframes: int, span_s: float, cfg: BackendConfig) -> float | None:
    """The scale-std gate (fraction of the scale) a monocular start's alignment is tried with
    on a window of ``n_keyframes`` keyframes spanning ``span_s`` seconds; None: not tried yet.

    ``mono_init_keyframes`` keyframes (or, with ``mono_init_span_s``, at least
    ``mono_init_span_keyframes`` spanning that long) are tried under ``mono_init_max_scale_std``;
    with ``mono_init_early_max_scale_std`` fewer (from ``mono_init_span_keyframes``) are tried
    under that stricter gate: a well-excited window starts at once, a gentle one waits."""
    if span_s < cfg.mono_init_min_span_s:
        return None
    if n_keyframes >= cfg.mono_init_keyframes:
        return cfg.mono_init_max_scale_std
    if n_keyframes < cfg.mono_init_span_keyframes:
        return None
    if cfg.mono_init_span_s > 0 and span_s >= cfg.mono_init_span_s:
        return cfg.mono_init_max_scale_std
    if cfg.mono_init_early_max_scale_std > 0:
        return min(cfg.mono_init_early_max_scale_std, cfg.mono_init_max_scale_std)
    return None


def _preintegrated(
    params: gtsam.PreintegrationCombinedParams,
    pieces: list[tuple[np.ndarray, np.ndarray, np.ndarray]],
    bias_gyro: np.ndarray,
) -> list[tuple[float, np.ndarray, np.ndarray, np.ndarray, np.ndarray]]:
    """(dt, dp, dv, d dp / d ba, d dv / d ba) of every interval, preintegrated about the gyro
    bias and a zero accelerometer bias (the Jacobians numeric, through GTSAM's first-order
    bias correction, as :func:`slam.backend.init.moving_init`)."""
    out = []
    bias = make_bias(bias_gyro, np.zeros(3))
    gravity_n = np.asarray(params.n_gravity, dtype=float)
    eps = 1e-3
    for p in pieces:
        pim = gtsam.PreintegratedCombinedMeasurements(params, bias)
        integrate_pieces(pim, p)
        _, dv0, dp0 = bias_corrected_deltas(pim, bias_gyro, np.zeros(3), gravity_n)
        jp, jv = np.zeros((3, 3)), np.zeros((3, 3))
        for a in range(3):
            ba = np.zeros(3)
            ba[a] = eps
            _, dva, dpa = bias_corrected_deltas(pim, bias_gyro, ba, gravity_n)
            jp[:, a], jv[:, a] = (dpa - dp0) / eps, (dva - dv0) / eps
        out.append((pim.deltaTij(), dp0, dv0, jp, jv))
    return out


def _keyframe_pieces(
    t_kf_ns: np.ndarray,
    imu_t_ns: np.ndarray,
    imu_gyro_rad_s: np.ndarray,
    imu_accel_m_s2: np.ndarray,
    imu_gap_max_s: float,
) -> list | None:
    """The IMU's pieces (:func:`integration_pieces`) over each interval between consecutive
    keyframes; None when one interval is not covered."""
    pieces = []
    for i in range(len(t_kf_ns) - 1):
        p = integration_pieces(
            imu_t_ns, imu_gyro_rad_s, imu_accel_m_s2, int(t_kf_ns[i]), int(t_kf_ns[i + 1]),
            imu_gap_max_s,
        )  # fmt: skip
        if p is None:
            return None
        pieces.append(p)
    return pieces


def _solve(
    deltas: list[tuple[float, np.ndarray, np.ndarray, np.ndarray, np.ndarray]],
    rot: np.ndarray,
    centres: np.ndarray,
    lever_m: np.ndarray,
    gravity_m_s2: float,
    gravity_dir: np.ndarray | None,
    accel_bias_sigma_m_s2: float,
) -> tuple[float, np.ndarray, np.ndarray, np.ndarray, float]:
    """Least squares of the module docstring's equations over keyframes 0..len(deltas), with
    an accelerometer bias held near 0 by a prior of ``accel_bias_sigma_m_s2``.
    ``gravity_dir`` None: g free (3 unknowns); else ``|g| dir + basis w`` (2 unknowns).
    Returns (s, g, v (K, 3), ba, the standard deviation of s from the fit's residuals)."""
    k_count = len(deltas) + 1
    n_v = 3 * k_count
    n_g = 3 if gravity_dir is None else 2
    i_s = n_v + n_g
    n = i_s + 4
    a_rows, b_rows = [], []
    g0 = np.zeros(3)
    basis = np.zeros((3, 2))
    if gravity_dir is not None:
        g0 = gravity_m_s2 * gravity_dir
        basis = np.linalg.svd(gravity_dir.reshape(1, 3))[2][1:].T * gravity_m_s2
    for i, (dt, dp, dv, jp, jv) in enumerate(deltas):
        j = i + 1
        ap = np.zeros((3, n))
        ap[:, 3 * i : 3 * i + 3] = -dt * np.eye(3)
        ap[:, i_s] = centres[j] - centres[i]
        ap[:, i_s + 1 :] = -rot[i] @ jp
        bp = rot[i] @ dp + (rot[j] - rot[i]) @ lever_m
        av = np.zeros((3, n))
        av[:, 3 * i : 3 * i + 3] = -np.eye(3)
        av[:, 3 * j : 3 * j + 3] = np.eye(3)
        av[:, i_s + 1 :] = -rot[i] @ jv
        bv = rot[i] @ dv
        if gravity_dir is None:
            ap[:, n_v : n_v + 3] = -0.5 * dt * dt * np.eye(3)
            av[:, n_v : n_v + 3] = -dt * np.eye(3)
        else:
            ap[:, n_v : n_v + 2] = -0.5 * dt * dt * basis
            bp = bp + 0.5 * dt * dt * g0
            av[:, n_v : n_v + 2] = -dt * basis
            bv = bv + dt * g0
        # position rows in metres over ~dt, velocity rows in m/s: weigh them alike per second
        a_rows += [ap / max(dt, 1e-3), av]
        b_rows += [bp / max(dt, 1e-3), bv]
    prior = np.zeros((3, n))
    prior[:, i_s + 1 :] = np.eye(3) / accel_bias_sigma_m_s2
    a_rows.append(prior)
    b_rows.append(np.zeros(3))
    a_mat, b_vec = np.vstack(a_rows), np.concatenate(b_rows)
    x = np.linalg.lstsq(a_mat, b_vec, rcond=None)[0]
    v = x[:n_v].reshape(k_count, 3)
    g = x[n_v : n_v + 3] if gravity_dir is None else g0 + basis @ x[n_v : n_v + 2]
    # the scale's standard deviation: residual variance times (A^T A)^-1
    dof = max(len(b_vec) - n, 1)
    var = float(np.sum((a_mat @ x - b_vec) ** 2)) / dof
    try:
        scale_std = float(np.sqrt(var * np.linalg.inv(a_mat.T @ a_mat)[i_s, i_s]))
    except np.linalg.LinAlgError:
        scale_std = float("inf")
    return float(x[i_s]), g, v, x[i_s + 1 :], scale_std


def refine_vo_poses(
    world_from_body_vo: np.ndarray,
    observations: list[tuple[np.ndarray, np.ndarray]],
    points_vo: dict[int, np.ndarray],
    intrinsics_k: np.ndarray,
    body_from_cam0: np.ndarray,
    pixel_sigma_px: float = 1.0,
    iterations: int = 15,
) -> np.ndarray:
    """Bundle adjustment of up-to-scale keyframe poses (K, 4, 4) and the landmarks they share.

    ``observations[k]``: (landmark ids (N,), undistorted pixels (N, 2)) of keyframe k;
    ``points_vo``: a starting position per landmark id. Landmarks seen by fewer than two
    keyframes are left out. The first pose is held by a tight prior and the last one's
    position by a loose one (the scale gauge; the alignment finds the metric scale). Returns
    the refined poses at the input's scale (the camera centres' spread from the first one
    kept), or the input when the problem is too small or the solver fails."""
    counts: dict[int, int] = {}
    for ids, _ in observations:
        for lid in ids.tolist():
            counts[lid] = counts.get(lid, 0) + 1
    used = {lid for lid, c in counts.items() if c >= 2 and lid in points_vo}
    k_count = len(world_from_body_vo)
    if len(used) < 20 or k_count < 2:
        return world_from_body_vo
    cal = gtsam.Cal3_S2(
        intrinsics_k[0, 0], intrinsics_k[1, 1], 0.0, intrinsics_k[0, 2], intrinsics_k[1, 2]
    )
    body_p_cam = gtsam.Pose3(np.asarray(body_from_cam0, float))
    noise = gtsam.noiseModel.Robust.Create(
        gtsam.noiseModel.mEstimator.Huber.Create(1.345),
        gtsam.noiseModel.Isotropic.Sigma(2, pixel_sigma_px),
    )
    graph = gtsam.NonlinearFactorGraph()
    values = gtsam.Values()
    span = float(np.linalg.norm(world_from_body_vo[-1, :3, 3] - world_from_body_vo[0, :3, 3]))
    for k in range(k_count):
        values.insert(gtsam.symbol("x", k), gtsam.Pose3(world_from_body_vo[k]))
    graph.add(
        gtsam.PriorFactorPose3(
            gtsam.symbol("x", 0),
            gtsam.Pose3(world_from_body_vo[0]),
            gtsam.noiseModel.Isotropic.Sigma(6, 1e-6),
        )
    )
    graph.add(
        gtsam.PoseTranslationPrior3D(
            gtsam.symbol("x", k_count - 1),
            gtsam.Pose3(world_from_body_vo[-1]),
            gtsam.noiseModel.Isotropic.Sigma(3, max(0.2 * span, 1e-3)),
        )
    )
    for lid in used:
        values.insert(gtsam.symbol("l", lid), np.asarray(points_vo[lid], float))
    for k, (ids, px) in enumerate(observations):
        for lid, uv in zip(ids.tolist(), px, strict=True):
            if lid in used and np.all(np.isfinite(uv)):
                graph.add(
                    gtsam.GenericProjectionFactorCal3_S2(
                        np.asarray(uv, float),
                        noise,
                        gtsam.symbol("x", k),
                        gtsam.symbol("l", lid),
                        cal,
                        body_p_cam,
                    )
                )
    params = gtsam.LevenbergMarquardtParams()
    params.setMaxIterations(iterations)
    try:
        result = gtsam.LevenbergMarquardtOptimizer(graph, values, params).optimize()
    except RuntimeError:
        return world_from_body_vo
    out = np.array([result.atPose3(gtsam.symbol("x", k)).matrix() for k in range(k_count)])
    # back to the input's scale (the loose prior lets it move): the caller's scale is the one
    # the front end's map has, and the alignment's scale is applied to that map
    lever = np.asarray(body_from_cam0, float)[:3, 3]
    c_in = world_from_body_vo[:, :3, 3] + world_from_body_vo[:, :3, :3] @ lever
    c_out = out[:, :3, 3] + out[:, :3, :3] @ lever
    d_in = np.linalg.norm(c_in[1:] - c_in[0], axis=1)
    d_out = np.linalg.norm(c_out[1:] - c_out[0], axis=1)
    if not np.all(np.isfinite(out)) or d_out.sum() <= 0:
        return world_from_body_vo
    ratio = float(d_in.sum() / d_out.sum())
    c_out = c_in[0] + (c_out - c_out[0]) * ratio
    out[:, :3, 3] = c_out - out[:, :3, :3] @ lever
    return out


def align_mono(
    t_kf_ns: np.ndarray,
    world_from_body_vo: np.ndarray,
    body_from_cam0: np.ndarray,
    imu_t_ns: np.ndarray,
    imu_gyro_rad_s: np.ndarray,
    imu_accel_m_s2: np.ndarray,
    imu: ImuCalibration,
    imu_gap_max_s: float,
    max_gravity_error_m_s2: float,
    max_scale_disagreement: float,
    accel_bias_sigma_m_s2: float = 0.1,
    max_scale_std: float = 0.02,
    retry_accel_bias_sigma_m_s2: float = 0.0,
) -> MonoAlignment | None:
    """Align K >= 4 up-to-scale keyframe poses with the IMU (module docstring). None when the
    IMU does not cover every interval; else a :class:`MonoAlignment`, accepted or not.

    ``retry_accel_bias_sigma_m_s2`` > 0: the same keyframes are also aligned with this (looser)
    accelerometer-bias prior, whose scale's std is the honest one when the bias matters. The
    held solution is kept when it passed and the free one's scale is within two of its standard
    deviations; else the free one when it passes the checks (its bias, scale, gravity and
    velocities); else the alignment is rejected."""
    k_count = len(t_kf_ns)
    if k_count < 4:
        return None
    params = preintegration_params(imu)
    pieces = _keyframe_pieces(t_kf_ns, imu_t_ns, imu_gyro_rad_s, imu_accel_m_s2, imu_gap_max_s)
    if pieces is None:
        return None
    rot = world_from_body_vo[:, :3, :3]
    lever_m = np.asarray(body_from_cam0, float)[:3, 3]
    centres = world_from_body_vo[:, :3, 3] + rot @ lever_m
    bias_gyro, _ = estimate_gyro_bias(params, pieces, rot)
    deltas = _preintegrated(params, pieces, bias_gyro)

    def aligned(bias_sigma_m_s2: float) -> MonoAlignment:
        fit = _fit(deltas, rot, centres, lever_m, imu.gravity_m_s2, bias_sigma_m_s2)
        return _checked(fit, bias_gyro, imu.gravity_m_s2, max_gravity_error_m_s2,
                        max_scale_disagreement, max_scale_std, bias_sigma_m_s2)  # fmt: skip

    res = aligned(accel_bias_sigma_m_s2)
    if retry_accel_bias_sigma_m_s2 <= 0:
        return res
    free = aligned(retry_accel_bias_sigma_m_s2)
    if res.accepted and abs(res.scale - free.scale) <= 2.0 * free.scale_std:
        return res  # the bias does not matter here: the held solution, as without the retry
    if free.accepted:
        return free
    if res.accepted:  # the held scale is not the free one's, which is too uncertain yet
        reason = f"scale {res.scale:.3f} with the bias held, {free.scale:.3f} free"
        return dataclasses.replace(res, accepted=False, reason=reason)
    return res


def _fit(
    deltas: list[tuple[float, np.ndarray, np.ndarray, np.ndarray, np.ndarray]],
    rot: np.ndarray,
    centres: np.ndarray,
    lever_m: np.ndarray,
    g_norm: float,
    accel_bias_sigma_m_s2: float,
) -> tuple[float, np.ndarray, np.ndarray, np.ndarray, float, float, float]:
    """The alignment of :func:`align_mono` with one accelerometer-bias prior: (scale, gravity,
    velocities, ba, the scale's std, |g| of the free solution, the first two thirds' scale)."""
    _, g_free, _, _, _ = _solve(deltas, rot, centres, lever_m, g_norm, None, accel_bias_sigma_m_s2)
    g_free_norm = float(np.linalg.norm(g_free))

    def refined(part: list[Any]) -> tuple[float, np.ndarray, np.ndarray, np.ndarray, float]:
        g_dir = g_free / max(g_free_norm, 1e-9)
        s, g, v, ba, sd = 0.0, g_free, np.zeros((len(part) + 1, 3)), np.zeros(3), np.inf
        for _ in range(4):
            s, g, v, ba, sd = _solve(
                part, rot, centres, lever_m, g_norm, g_dir, accel_bias_sigma_m_s2
            )
            g_dir = g / np.linalg.norm(g)
        return s, g_dir * g_norm, v, ba, sd

    scale, gravity, vel, bias_accel, scale_std = refined(deltas)
    sub = max(3, (2 * len(deltas)) // 3)
    scale_sub = refined(deltas[:sub])[0] if sub < len(deltas) else scale
    return scale, gravity, vel, bias_accel, scale_std, g_free_norm, scale_sub


def _checked(
    fit: tuple[float, np.ndarray, np.ndarray, np.ndarray, float, float, float],
    bias_gyro: np.ndarray,
    g_norm: float,
    max_gravity_error_m_s2: float,
    max_scale_disagreement: float,
    max_scale_std: float,
    accel_bias_sigma_m_s2: float,
) -> MonoAlignment:
    """A :func:`_fit` judged by the module docstring's checks."""
    scale, gravity, vel, bias_accel, scale_std, g_free_norm, scale_sub = fit
    reason = ""
    if not np.isfinite(g_free_norm) or abs(g_free_norm - g_norm) > max_gravity_error_m_s2:
        reason = f"|g| {g_free_norm:.2f} m/s^2 from the free solution"
    elif not (np.isfinite(scale) and scale > 0):
        reason = f"scale {scale:.3g} not positive"
    elif not scale_std <= max_scale_std * scale:
        reason = f"scale {scale:.3f} +- {scale_std / scale:.1%}: too little excitation"
    elif not (scale_sub > 0 and abs(scale_sub / scale - 1.0) <= max_scale_disagreement):
        reason = f"scale {scale:.3f} not reproduced by the first keyframes ({scale_sub:.3f})"
    return MonoAlignment(
        accepted=not reason,
        reason=reason,
        scale=scale,
        gravity_vo_m_s2=gravity,
        velocities_vo_m_s=vel,
        bias_gyro_rad_s=bias_gyro,
        bias_accel_m_s2=bias_accel,
        gravity_norm_free_m_s2=g_free_norm,
        scale_subset=scale_sub,
        scale_std=scale_std,
        accel_bias_sigma_m_s2=accel_bias_sigma_m_s2,
    )


@dataclass(frozen=True, eq=False)
class ScaleCheck:
    """The result of :func:`check_scale`."""

    scale: float
    """Metric metres per metre of the checked poses (1: the smoother's scale agrees)."""
    scale_std: float
    counted: bool
    """The alignment passed the start's checks (excitation, gravity, consistency)."""
    wrong: bool
    """Counted and off 1 by more than the tolerance."""
    velocity_m_s: np.ndarray
    """(3,) the newest keyframe's metric velocity from the alignment, the poses' frame."""
    residual_m: float = float("nan")
    """:func:`check_scale_by_imu_fit` only: the rms distance of the checked positions from the
    fitted IMU trajectory (a few mm when they are a similarity of one the IMU explains)."""


def check_scale(
    t_kf_ns: np.ndarray,
    world_from_body: np.ndarray,
    body_from_cam0: np.ndarray,
    imu_t_ns: np.ndarray,
    imu_gyro_rad_s: np.ndarray,
    imu_accel_m_s2: np.ndarray,
    imu: ImuCalibration,
    imu_gap_max_s: float,
    max_gravity_error_m_s2: float,
    max_scale_disagreement: float,
    max_scale_std: float,
    tolerance: float,
) -> ScaleCheck | None:
    """The start's alignment (:func:`align_mono`) run again on metric keyframe poses (a
    smoother's estimates of the last seconds): their scale agrees with the IMU when it comes
    out 1. None when the IMU does not cover the keyframes."""
    res = align_mono(
        t_kf_ns,
        world_from_body,
        body_from_cam0,
        imu_t_ns,
        imu_gyro_rad_s,
        imu_accel_m_s2,
        imu,
        imu_gap_max_s,
        max_gravity_error_m_s2,
        max_scale_disagreement,
        max_scale_std=max_scale_std,
    )
    if res is None:
        return None
    wrong = res.accepted and abs(res.scale - 1.0) > tolerance
    velocity = np.asarray(res.velocities_vo_m_s[-1], float)
    return ScaleCheck(res.scale, res.scale_std, res.accepted, wrong, velocity)


def scale_check_streak(streak: int, check: ScaleCheck) -> int:
    """The count of consecutive wrong checks off on the same side, signed (+ too large, -
    too small), after ``check``: a right or uncounted check resets it to 0, a wrong one on the
    other side to +-1 (``backend.mono_scale_check_repeats`` corrects at its magnitude)."""
    if not check.wrong:
        return 0
    side = 1 if check.scale > 1.0 else -1
    return streak + side if side * streak > 0 else side


def check_scale_by_imu_fit(
    t_kf_ns: np.ndarray,
    world_from_body: np.ndarray,
    imu_t_ns: np.ndarray,
    imu_gyro_rad_s: np.ndarray,
    imu_accel_m_s2: np.ndarray,
    imu: ImuCalibration,
    imu_gap_max_s: float,
    bias_gyro_rad_s: np.ndarray,
    max_scale_std: float,
    tolerance: float,
) -> ScaleCheck | None:
    """The scale of metric keyframe poses (a smoother's estimates in its gravity-aligned world,
    gravity ``-g z``) read the other way round from :func:`check_scale`: the *positions* are
    fitted as a similarity of the IMU's own trajectory over the window,

        p_k = a + b tau_k + s (P_k + JP_k ba)

    (``P_k``: the specific force, rotated by the poses' rotations and with gravity, integrated
    twice from keyframe 0 at rest; ``JP_k`` its accelerometer-bias Jacobian; ``a``, ``b``, ``s``,
    ``s ba`` linear unknowns). The noisy positions are on the measured side, so their noise does
    not shrink ``s``: the alignment, whose unknown scale multiplies position differences next to
    free velocities, reads metric poses 3-11 mm off the truth at 0.03-1.03 and a smoother's at
    0.06-0.58 (BENCHMARKS.md, scalecheck20). Returns ``scale`` = 1 / s (metric metres per metre of
    the poses, as :func:`check_scale`), its standard deviation from the residuals, the newest
    keyframe's metric velocity (``b / s + V_last + JV_last ba``) and the residual; counted when
    ``s`` > 0 and the std is under ``max_scale_std`` of the scale. None when the IMU does not
    cover the keyframes or there are fewer than 6."""
    k_count = len(t_kf_ns)
    if k_count < 6:
        return None
    params = preintegration_params(imu)
    pieces = _keyframe_pieces(t_kf_ns, imu_t_ns, imu_gyro_rad_s, imu_accel_m_s2, imu_gap_max_s)
    if pieces is None:
        return None
    deltas = _preintegrated(params, pieces, np.asarray(bias_gyro_rad_s, float))
    gravity = np.asarray(params.n_gravity, dtype=float)
    rot = world_from_body[:, :3, :3]
    pos_p = np.zeros((k_count, 3))
    vel_p = np.zeros((k_count, 3))
    jac_p = np.zeros((k_count, 3, 3))
    jac_v = np.zeros((k_count, 3, 3))
    tau = np.zeros(k_count)
    for i, (dt, dp, dv, jp, jv) in enumerate(deltas):
        pos_p[i + 1] = pos_p[i] + vel_p[i] * dt + 0.5 * gravity * dt * dt + rot[i] @ dp
        jac_p[i + 1] = jac_p[i] + jac_v[i] * dt + rot[i] @ jp
        vel_p[i + 1] = vel_p[i] + gravity * dt + rot[i] @ dv
        jac_v[i + 1] = jac_v[i] + rot[i] @ jv
        tau[i + 1] = tau[i] + dt
    a_mat = np.zeros((3 * k_count, 10))
    for k in range(k_count):
        rows = slice(3 * k, 3 * k + 3)
        a_mat[rows, 0:3] = np.eye(3)
        a_mat[rows, 3:6] = tau[k] * np.eye(3)
        a_mat[rows, 6] = pos_p[k]
        a_mat[rows, 7:10] = jac_p[k]
    b_vec = world_from_body[:, :3, 3].reshape(-1)
    x = np.linalg.lstsq(a_mat, b_vec, rcond=None)[0]
    res = b_vec - a_mat @ x
    var = float(res @ res) / max(len(b_vec) - 10, 1)
    try:
        s_std = float(np.sqrt(var * np.linalg.inv(a_mat.T @ a_mat)[6, 6]))
    except np.linalg.LinAlgError:
        return None
    s = float(x[6])
    residual = float(np.sqrt(res @ res / k_count))
    if not (np.isfinite(s) and s > 0 and np.isfinite(s_std)):
        return ScaleCheck(float("nan"), float("inf"), False, False, np.zeros(3), residual)
    scale = 1.0 / s
    scale_std = s_std / (s * s)
    counted = scale_std <= max_scale_std * scale
    velocity = x[3:6] / s + vel_p[-1] + jac_v[-1] @ (x[7:10] / s)
    wrong = counted and abs(scale - 1.0) > tolerance
    return ScaleCheck(scale, scale_std, counted, wrong, velocity, residual)


@dataclass(frozen=True, eq=False)
class BatchStart:
    """The result of :func:`batch_start`: the window's states after the visual-inertial bundle
    adjustment, and a prior that carries them into the fixed-lag smoother."""

    world_from_body: np.ndarray
    """(K, 4, 4) metric, gravity-aligned world."""
    velocities_m_s: np.ndarray
    """(K, 3) world frame."""
    biases: list[gtsam.imuBias.ConstantBias]
    prior: gtsam.NonlinearFactor
    """The newest state's joint marginal (pose, velocity, bias; a ``LinearContainerFactor`` on
    the caller's keys at the batch's solution): what the whole window says about it, with the
    correlations (the scale lives in the pose-velocity one)."""
    covariance: np.ndarray
    """(15, 15) that marginal's covariance: pose (rotation rad, position m; GTSAM's tangent),
    velocity m/s, bias (accelerometer m/s^2, gyro rad/s)."""
    scale_change: float
    """The camera centres' spread over the window after / before (1: the alignment's scale)."""
    landmarks: int
    observations: int
    error_before: float
    error_after: float


def batch_start(
    world_from_body: np.ndarray,
    velocities_m_s: np.ndarray,
    bias: gtsam.imuBias.ConstantBias,
    imu_factors: list[gtsam.PreintegratedCombinedMeasurements],
    observations: list[tuple[np.ndarray, np.ndarray]],
    points_world: dict[int, np.ndarray],
    intrinsics_k: np.ndarray,
    body_from_cam0: np.ndarray,
    newest_keys: tuple[int, int, int],
    pixel_sigma_px: float = 1.0,
    huber_k: float = 1.345,
    min_keyframes_per_landmark: int = 2,
    prior_pose_sigmas: tuple[float, float] = (0.01, 0.01),
    prior_bias_sigmas: tuple[float, float] = (0.1, 0.005),
    iterations: int = 30,
) -> BatchStart | None:
    """One visual-inertial bundle adjustment over the aligned window (K keyframes).

    Starts from the alignment's metric poses ``world_from_body`` (K, 4, 4), velocities (K, 3)
    and ``bias``; ``imu_factors[i]`` is the preintegration from keyframe i to i + 1 (as the
    smoother's); ``observations[k]`` = (landmark ids, undistorted cam0 pixels) of keyframe k,
    ``points_world`` a starting position per landmark (metric world). Landmarks seen by fewer
    than ``min_keyframes_per_landmark`` keyframes are left out. The gauge: the first pose held
    by a prior of ``prior_pose_sigmas`` (rad, m; its roll and pitch are also seen by the IMU),
    the first bias by ``prior_bias_sigmas`` (accelerometer, gyro) about ``bias``. Velocities,
    later poses and biases (random walk through the combined IMU factors) and the scale are
    free. ``newest_keys`` = (pose, velocity, bias) keys the returned prior is written on.
    None when the problem is too small or the solver or its marginals fail."""
    k_count = len(world_from_body)
    if k_count < 2 or len(imu_factors) != k_count - 1:
        return None
    counts: dict[int, int] = {}
    for ids, _ in observations:
        for lid in ids.tolist():
            counts[lid] = counts.get(lid, 0) + 1
    used = {
        lid
        for lid, c in counts.items()
        if c >= min_keyframes_per_landmark
        and lid in points_world
        and np.all(np.isfinite(points_world[lid]))
    }
    if len(used) < 20:
        return None

    def xk(k: int) -> int:
        return gtsam.symbol("x", k)

    def vk(k: int) -> int:
        return gtsam.symbol("v", k)

    def bk(k: int) -> int:
        return gtsam.symbol("b", k)

    graph = gtsam.NonlinearFactorGraph()
    values = gtsam.Values()
    for k in range(k_count):
        values.insert(xk(k), gtsam.Pose3(np.asarray(world_from_body[k], float)))
        values.insert(vk(k), np.asarray(velocities_m_s[k], float))
        values.insert(bk(k), bias)
    graph.add(
        gtsam.PriorFactorPose3(
            xk(0),
            gtsam.Pose3(np.asarray(world_from_body[0], float)),
            pose_noise(*prior_pose_sigmas),
        )
    )
    graph.add(gtsam.PriorFactorConstantBias(bk(0), bias, bias_noise(*prior_bias_sigmas)))
    for i, pim in enumerate(imu_factors):
        graph.add(
            gtsam.CombinedImuFactor(xk(i), vk(i), xk(i + 1), vk(i + 1), bk(i), bk(i + 1), pim)
        )
    cal = gtsam.Cal3_S2(
        intrinsics_k[0, 0], intrinsics_k[1, 1], 0.0, intrinsics_k[0, 2], intrinsics_k[1, 2]
    )
    body_p_cam = gtsam.Pose3(np.asarray(body_from_cam0, float))
    noise = gtsam.noiseModel.Robust.Create(
        gtsam.noiseModel.mEstimator.Huber.Create(huber_k),
        gtsam.noiseModel.Isotropic.Sigma(2, pixel_sigma_px),
    )
    for lid in sorted(used):
        values.insert(gtsam.symbol("l", lid), np.asarray(points_world[lid], float))
    n_obs = 0
    for k, (ids, px) in enumerate(observations):
        for lid, uv in zip(ids.tolist(), np.asarray(px, float), strict=True):
            if lid in used and np.all(np.isfinite(uv)):
                graph.add(
                    gtsam.GenericProjectionFactorCal3_S2(
                        uv, noise, xk(k), gtsam.symbol("l", lid), cal, body_p_cam
                    )
                )
                n_obs += 1
    params = gtsam.LevenbergMarquardtParams()
    params.setMaxIterations(iterations)
    try:
        error_before = float(graph.error(values))
        result = gtsam.LevenbergMarquardtOptimizer(graph, values, params).optimize()
        last = k_count - 1
        joint = gtsam.Marginals(graph, result).jointMarginalCovariance(
            [xk(last), vk(last), bk(last)]
        )
        keys = [xk(last), vk(last), bk(last)]
        cov = np.block([[joint.at(a, b) for b in keys] for a in keys])
    except RuntimeError:
        return None
    poses = np.array([result.atPose3(xk(k)).matrix() for k in range(k_count)])
    vels = np.array([result.atVector(vk(k)) for k in range(k_count)])
    if not (np.all(np.isfinite(poses)) and np.all(np.isfinite(vels)) and np.all(np.isfinite(cov))):
        return None
    lever = np.asarray(body_from_cam0, float)[:3, 3]
    c_in = world_from_body[:, :3, 3] + world_from_body[:, :3, :3] @ lever
    c_out = poses[:, :3, 3] + poses[:, :3, :3] @ lever
    spread_in = float(np.linalg.norm(c_in - c_in.mean(axis=0), axis=1).sum())
    spread_out = float(np.linalg.norm(c_out - c_out.mean(axis=0), axis=1).sum())
    return BatchStart(
        world_from_body=poses,
        velocities_m_s=vels,
        biases=[result.atConstantBias(bk(k)) for k in range(k_count)],
        prior=_joint_prior(cov, newest_keys, result, (xk(last), vk(last), bk(last))),
        covariance=cov,
        scale_change=spread_out / max(spread_in, 1e-12),
        landmarks=len(used),
        observations=n_obs,
        error_before=error_before,
        error_after=float(graph.error(result)),
    )


def _joint_prior(
    covariance: np.ndarray,
    keys: tuple[int, int, int],
    solution: gtsam.Values,
    solution_keys: tuple[int, int, int],
) -> gtsam.NonlinearFactor:
    """A Gaussian prior on (pose, velocity, bias) ``keys`` with this joint ``covariance``
    about their values in ``solution`` (at ``solution_keys``): the whitened Jacobian factor
    ``R d = 0`` (``R^T R`` the information) linearised at the solution."""
    info = np.linalg.inv(covariance)
    info = 0.5 * (info + info.T)
    r = np.linalg.cholesky(info).T  # upper: info = r^T r
    factor = gtsam.JacobianFactor(
        keys[0], r[:, 0:6], keys[1], r[:, 6:9], keys[2], r[:, 9:15], np.zeros(15),
        gtsam.noiseModel.Unit.Create(15),
    )  # fmt: skip
    lin = gtsam.Values()
    lin.insert(keys[0], solution.atPose3(solution_keys[0]))
    lin.insert(keys[1], solution.atVector(solution_keys[1]))
    lin.insert(keys[2], solution.atConstantBias(solution_keys[2]))
    return gtsam.LinearContainerFactor(factor, lin)

"""Initialisation of the visual-inertial state: still start and moving start.

Still start: the IMU is still over a window; gravity direction (roll/pitch) and gyro bias come
from a linear Kalman filter (filterpy, imported lazily) over the window's readings, state
``[specific force in body (3), gyro bias (3)]``; :func:`still_init_align` is the scipy
``Rotation.align_vectors``-on-the-mean-accel alternative used for comparison.

Moving start (VINS-Mono / ORB-SLAM3 style inertial alignment, stereo so scale = 1): visual-only
poses of the first keyframes (``Keyframe.world_from_body_vo``) and the IMU preintegrated between
them give (1) the gyro bias by rotation alignment (Gauss-Newton on the relative rotations), (2)
gravity and every keyframe velocity by linear least squares, (3) a refinement with |g| fixed to
its known magnitude (2-DoF tangent update) plus an accelerometer bias with a weak prior.

After initialisation the world frame is gravity aligned (z up): ``world_from_vo`` is the smallest
rotation (about the first keyframe's position) that turns the VO frame's gravity to -z, so the
first keyframe keeps its VO position and heading as far as gravity allows.
"""

from __future__ import annotations

from dataclasses import dataclass

import gtsam
import numpy as np
from scipy.spatial.transform import Rotation

from slam.backend.config import BackendConfig
from slam.backend.imu import integrate_pieces, integration_pieces, make_bias, preintegration_params
from slam.core.calibration import ImuCalibration
from slam.core.geometry import make_transform, so3_log

Z_UP = np.array([0.0, 0.0, 1.0])


def minimal_rotation(from_dir: np.ndarray, to_dir: np.ndarray) -> np.ndarray:
    """The smallest rotation R (3x3) with R @ from_dir ∥ to_dir."""
    a = np.asarray(from_dir, dtype=float) / np.linalg.norm(from_dir)
    b = np.asarray(to_dir, dtype=float) / np.linalg.norm(to_dir)
    axis = np.cross(a, b)
    s = np.linalg.norm(axis)
    angle = np.arctan2(s, float(a @ b))
    if s < 1e-12:
        if a @ b > 0:
            return np.eye(3)
        perp = np.cross(a, [1.0, 0.0, 0.0])
        if np.linalg.norm(perp) < 1e-6:
            perp = np.cross(a, [0.0, 1.0, 0.0])
        return Rotation.from_rotvec(np.pi * perp / np.linalg.norm(perp)).as_matrix()
    return Rotation.from_rotvec(axis / s * angle).as_matrix()


def world_from_vo_gravity(gravity_up_vo: np.ndarray, origin_vo: np.ndarray) -> np.ndarray:
    """4x4 world_from_vo: minimal rotation taking the VO 'up' to +z, about ``origin_vo``."""
    rot = minimal_rotation(gravity_up_vo, Z_UP)
    origin = np.asarray(origin_vo, dtype=float)
    return make_transform(rot, origin - rot @ origin)


# --- still start -------------------------------------------------------------------------------


def _moving_average(x: np.ndarray, n: int) -> np.ndarray:
    c = np.cumsum(np.vstack([np.zeros((1, x.shape[1])), x]), axis=0)
    return (c[n:] - c[:-n]) / n


def is_still(
    gyro_rad_s: np.ndarray, accel_m_s2: np.ndarray, config: BackendConfig, rate_hz: float
) -> bool:
    """Still test over a window: small std of every smoothed accel and gyro axis."""
    n = max(1, int(round(config.still_smoothing_s * rate_hz)))
    if len(gyro_rad_s) < 2 * n + 5:
        return False
    accel_std = float(_moving_average(np.asarray(accel_m_s2, float), n).std(axis=0).max())
    gyro_std = float(_moving_average(np.asarray(gyro_rad_s, float), n).std(axis=0).max())
    return accel_std < config.still_accel_std_m_s2 and gyro_std < config.still_gyro_std_rad_s


def find_still_prefix(
    t_ns: np.ndarray, gyro_rad_s: np.ndarray, accel_m_s2: np.ndarray, config: BackendConfig
) -> int:
    """Number of leading samples over which the IMU stays still (0 if the first window is not).

    Grows the interval by half-windows while every window of ``still_window_s`` stays still.
    """
    window_ns = int(config.still_window_s * 1e9)
    if len(t_ns) == 0 or t_ns[-1] - t_ns[0] < window_ns:
        return 0
    end = 0
    start_ns = int(t_ns[0])
    while True:
        i0 = int(np.searchsorted(t_ns, start_ns))
        i1 = int(np.searchsorted(t_ns, start_ns + window_ns))
        rate_hz = (i1 - i0) / config.still_window_s
        if i1 >= len(t_ns) or not is_still(gyro_rad_s[i0:i1], accel_m_s2[i0:i1], config, rate_hz):
            return end
        end = i1
        start_ns += window_ns // 2


@dataclass(frozen=True, eq=False)
class StillInitResult:
    """Gravity direction and gyro bias from a still interval."""

    up_body: np.ndarray  # (3,) unit vector: +z of a gravity-aligned world, in the body frame
    bias_gyro_rad_s: np.ndarray  # (3,)
    accel_norm_m_s2: float  # mean specific-force magnitude (≈ g + accel-bias projection)
    n_samples: int

    def world_from_body_rotation(self) -> np.ndarray:
        """A gravity-aligned world_from_body rotation (the smallest one; yaw is free)."""
        return minimal_rotation(self.up_body, Z_UP)


def still_init_kalman(
    gyro_rad_s: np.ndarray, accel_m_s2: np.ndarray, imu: ImuCalibration
) -> StillInitResult:
    """Kalman-filter estimate of the specific force (gravity up, body frame) and gyro bias.

    Linear KF, state ``[f_body (3), b_gyro (3)]``, constant model (bias random walk as process
    noise), measurement = the raw readings with the discrete white-noise variances.
    """
    from filterpy.kalman import KalmanFilter  # lazy: filterpy imports in ~1 s

    gyro = np.asarray(gyro_rad_s, dtype=float)
    accel = np.asarray(accel_m_s2, dtype=float)
    dt = 1.0 / imu.rate_hz
    kf = KalmanFilter(dim_x=6, dim_z=6)
    kf.x = np.concatenate([accel[0], gyro[0]]).reshape(6, 1)
    kf.F = np.eye(6)
    kf.H = np.eye(6)
    kf.P = np.diag([1.0] * 3 + [0.1] * 3)
    # Discrete white-noise variance = density^2 / dt; vibration dominates on a real vehicle, so
    # the accel variance is floored at (0.05 m/s^2)^2 (it only sets the gain, not the limit).
    var_a = max(imu.accel_noise_density**2 / dt, 0.05**2)
    var_g = max(imu.gyro_noise_density**2 / dt, 0.002**2)
    kf.R = np.diag([var_a] * 3 + [var_g] * 3)
    kf.Q = np.diag([1e-12] * 3 + [imu.gyro_random_walk**2 * dt] * 3)
    for k in range(len(gyro)):
        kf.predict()
        kf.update(np.concatenate([accel[k], gyro[k]]).reshape(6, 1))
    x = kf.x.reshape(6)
    f = x[:3]
    return StillInitResult(
        up_body=f / np.linalg.norm(f),
        bias_gyro_rad_s=x[3:].copy(),
        accel_norm_m_s2=float(np.linalg.norm(f)),
        n_samples=len(gyro),
    )


def still_init_align(gyro_rad_s: np.ndarray, accel_m_s2: np.ndarray) -> StillInitResult:
    """The reference: scipy align_vectors on the mean accel, gyro bias = mean gyro."""
    mean_accel = np.asarray(accel_m_s2, dtype=float).mean(axis=0)
    rot, _ = Rotation.align_vectors([Z_UP], [mean_accel])  # world_from_body
    up_body = rot.inv().apply(Z_UP)
    return StillInitResult(
        up_body=up_body,
        bias_gyro_rad_s=np.asarray(gyro_rad_s, dtype=float).mean(axis=0),
        accel_norm_m_s2=float(np.linalg.norm(mean_accel)),
        n_samples=len(gyro_rad_s),
    )


# --- moving start ------------------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class MovingInitResult:
    """Inertial alignment of visual-only keyframe poses (all in the VO frame)."""

    gravity_vo_m_s2: np.ndarray  # (3,) gravity vector (pointing down) in the VO frame
    velocities_vo_m_s: np.ndarray  # (K, 3) body velocity of every keyframe in the VO frame
    bias_gyro_rad_s: np.ndarray  # (3,)
    bias_accel_m_s2: np.ndarray  # (3,)
    gravity_norm_unconstrained_m_s2: float  # |g| of the free linear solution (a health check)
    rotation_residual_rad: float  # RMS rotation misfit after the gyro-bias fit

    def world_from_vo(self, origin_vo: np.ndarray) -> np.ndarray:
        """Gravity-aligned world_from_vo (see the module docstring)."""
        return world_from_vo_gravity(-self.gravity_vo_m_s2, origin_vo)


def _preintegrate_all(
    params: gtsam.PreintegrationCombinedParams,
    pieces: list[tuple[np.ndarray, np.ndarray, np.ndarray]],
    bias_gyro: np.ndarray,
) -> list[gtsam.PreintegratedCombinedMeasurements]:
    """Preintegrate every interval about the current gyro-bias estimate (accel bias 0)."""
    out = []
    bias_hat = make_bias(bias_gyro, np.zeros(3))
    for p in pieces:
        pim = gtsam.PreintegratedCombinedMeasurements(params, bias_hat)
        integrate_pieces(pim, p)
        out.append(pim)
    return out


def bias_corrected_deltas(
    pim: gtsam.PreintegratedCombinedMeasurements,
    bias_gyro: np.ndarray,
    bias_accel: np.ndarray,
    gravity_n: np.ndarray,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Bias-corrected (first order, GTSAM's Jacobians) ΔR, Δv, Δp of one preintegration."""
    dt = pim.deltaTij()
    nav = pim.predict(
        gtsam.NavState(gtsam.Rot3(), np.zeros(3), np.zeros(3)), make_bias(bias_gyro, bias_accel)
    )
    d_rot = nav.attitude().matrix()
    d_v = nav.velocity() - gravity_n * dt
    d_p = nav.position() - 0.5 * gravity_n * dt * dt
    return d_rot, d_v, d_p


def estimate_gyro_bias(
    params: gtsam.PreintegrationCombinedParams,
    pieces: list[tuple[np.ndarray, np.ndarray, np.ndarray]],
    rot_vo: np.ndarray,
) -> tuple[np.ndarray, float]:
    """Gyro bias from visual relative rotations ``rot_vo`` (K, 3, 3) against the IMU pieces
    between them: Gauss-Newton on sum ||Log(dR(bg)^T R_i^T R_j)||^2, re-integrating about the
    current estimate each iteration (numeric Jacobian through GTSAM's bias correction).
    Returns (bias, RMS rotation residual in rad). Used by the stereo moving start and the
    monocular alignment (``slam.backend.mono_init``)."""
    gravity_n = np.asarray(params.n_gravity, dtype=float)  # rotations ignore it
    bias_gyro = np.zeros(3)
    zero3 = np.zeros(3)
    res_rms = 0.0
    for _ in range(3):
        pims = _preintegrate_all(params, pieces, bias_gyro)
        rows = []
        resid = []
        eps = 1e-4
        for i, pim in enumerate(pims):
            rel = rot_vo[i].T @ rot_vo[i + 1]
            d0, _, _ = bias_corrected_deltas(pim, bias_gyro, zero3, gravity_n)
            r0 = so3_log(d0.T @ rel)
            jac = np.zeros((3, 3))
            for a in range(3):
                db = bias_gyro.copy()
                db[a] += eps
                da, _, _ = bias_corrected_deltas(pim, db, zero3, gravity_n)
                jac[:, a] = (so3_log(da.T @ rel) - r0) / eps
            rows.append(jac)
            resid.append(r0)
        jac_all = np.vstack(rows)
        r_all = np.concatenate(resid)
        step = np.linalg.lstsq(jac_all, -r_all, rcond=None)[0]
        bias_gyro = bias_gyro + step
        res_rms = float(np.sqrt(np.mean(r_all**2)))
        if np.linalg.norm(step) < 1e-7:
            break
    return bias_gyro, res_rms


def moving_init(
    t_kf_ns: np.ndarray,
    world_from_body_vo: np.ndarray,
    imu_t_ns: np.ndarray,
    imu_gyro_rad_s: np.ndarray,
    imu_accel_m_s2: np.ndarray,
    imu: ImuCalibration,
    config: BackendConfig,
    position_sigma_m: float = 0.01,
    velocity_sigma_m_s: float = 0.02,
    accel_bias_prior_sigma_m_s2: float = 0.1,
) -> MovingInitResult | None:
    """Align K >= 3 visual-only keyframe poses with the IMU; None if the IMU does not cover them."""
    k_count = len(t_kf_ns)
    if k_count < 3:
        return None
    params = preintegration_params(imu)
    gravity_n = np.array([0.0, 0.0, -imu.gravity_m_s2])
    pieces = []
    for i in range(k_count - 1):
        p = integration_pieces(
            imu_t_ns,
            imu_gyro_rad_s,
            imu_accel_m_s2,
            int(t_kf_ns[i]),
            int(t_kf_ns[i + 1]),
            config.imu_gap_max_s,
        )
        if p is None:
            return None
        pieces.append(p)
    rot_vo = world_from_body_vo[:, :3, :3]
    pos_vo = world_from_body_vo[:, :3, 3]

    # 1) gyro bias from the relative rotations
    bias_gyro, res_rms = estimate_gyro_bias(params, pieces, rot_vo)
    zero3 = np.zeros(3)
    pims = _preintegrate_all(params, pieces, bias_gyro)

    def solve(gravity_dir: np.ndarray | None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Weighted LS for velocities, gravity (free 3-vector, or a 2-DoF tangent update of a
        fixed-magnitude direction) and accel bias (weak prior). Returns (v, g, ba)."""
        n_v = 3 * k_count
        n_g = 3 if gravity_dir is None else 2
        n = n_v + n_g + 3
        a_rows: list[np.ndarray] = []
        b_rows: list[np.ndarray] = []
        if gravity_dir is not None:
            g0 = imu.gravity_m_s2 * gravity_dir
            basis = np.linalg.svd(gravity_dir.reshape(1, 3))[2][1:].T * imu.gravity_m_s2  # (3, 2)
        eps = 1e-3
        for i, pim in enumerate(pims):
            dt = pim.deltaTij()
            _, dv0, dp0 = bias_corrected_deltas(pim, bias_gyro, zero3, gravity_n)
            jv = np.zeros((3, 3))
            jp = np.zeros((3, 3))
            for a in range(3):
                ba = np.zeros(3)
                ba[a] = eps
                _, dva, dpa = bias_corrected_deltas(pim, bias_gyro, ba, gravity_n)
                jv[:, a] = (dva - dv0) / eps
                jp[:, a] = (dpa - dp0) / eps
            ri = rot_vo[i]
            # position: v_i dt + 0.5 g dt^2 + R_i (dp0 + Jp ba) = p_j - p_i
            ap = np.zeros((3, n))
            ap[:, 3 * i : 3 * i + 3] = np.eye(3) * dt
            bp = pos_vo[i + 1] - pos_vo[i] - ri @ dp0
            # velocity: v_j - v_i - g dt - R_i (dv0 + Jv ba) = 0
            av = np.zeros((3, n))
            av[:, 3 * i : 3 * i + 3] = -np.eye(3)
            av[:, 3 * i + 3 : 3 * i + 6] = np.eye(3)
            bv = ri @ dv0
            if gravity_dir is None:
                ap[:, n_v : n_v + 3] = 0.5 * dt * dt * np.eye(3)
                av[:, n_v : n_v + 3] = -dt * np.eye(3)
            else:
                ap[:, n_v : n_v + 2] = 0.5 * dt * dt * basis
                bp = bp - 0.5 * dt * dt * g0
                av[:, n_v : n_v + 2] = -dt * basis
                bv = bv + dt * g0
            ap[:, n_v + n_g :] = ri @ jp
            av[:, n_v + n_g :] = -ri @ jv
            a_rows += [ap / position_sigma_m, av / velocity_sigma_m_s]
            b_rows += [bp / position_sigma_m, bv / velocity_sigma_m_s]
        prior = np.zeros((3, n))
        prior[:, n_v + n_g :] = np.eye(3) / accel_bias_prior_sigma_m_s2
        a_rows.append(prior)
        b_rows.append(np.zeros(3))
        x = np.linalg.lstsq(np.vstack(a_rows), np.concatenate(b_rows), rcond=None)[0]
        v = x[:n_v].reshape(k_count, 3)
        if gravity_dir is None:
            g = x[n_v : n_v + 3]
        else:
            g = g0 + basis @ x[n_v : n_v + 2]
        return v, g, x[n_v + n_g :]

    _, g_free, _ = solve(None)
    g_norm_free = float(np.linalg.norm(g_free))
    if not np.isfinite(g_norm_free) or g_norm_free < 1e-6:
        return None
    g_dir = g_free / g_norm_free
    v = np.zeros((k_count, 3))
    ba = np.zeros(3)
    for _ in range(4):
        v, g, ba = solve(g_dir)
        g_dir = g / np.linalg.norm(g)
    return MovingInitResult(
        gravity_vo_m_s2=g_dir * imu.gravity_m_s2,
        velocities_vo_m_s=v,
        bias_gyro_rad_s=bias_gyro,
        bias_accel_m_s2=ba,
        gravity_norm_unconstrained_m_s2=g_norm_free,
        rotation_residual_rad=res_rms,
    )

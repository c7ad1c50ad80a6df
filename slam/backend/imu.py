"""IMU preintegration helpers and the back end's IMU buffer (a ``slam.imu_buffer.ImuBuffer``);
the noise models of the start's pose and bias priors (:func:`pose_noise`, :func:`bias_noise`).

Preintegration uses GTSAM's ``PreintegratedCombinedMeasurements`` (navigation frame z up,
gravity ``-g z``). Noise densities are Kalibr's continuous-time ones; GTSAM takes continuous-time
covariances (density^2) and discretises them itself (divides by dt for white noise, multiplies
by dt for bias random walks).

Between two keyframe times the samples are integrated piecewise: the knots are the two keyframe
times and every sample time strictly between them; each piece uses the mean of the
linearly-interpolated readings at its two knots (trapezoidal rule). The boundary intervals are
thus split exactly at the keyframe times.
"""

from __future__ import annotations

import gtsam
import numpy as np

from slam.backend.config import BackendConfig
from slam.core.calibration import ImuCalibration
from slam.core.geometry import so3_exp_batch
from slam.imu_buffer import ImuBuffer


def preintegration_params(
    imu: ImuCalibration, gyro_density: float | None = None, accel_density: float | None = None
) -> gtsam.PreintegrationCombinedParams:
    """GTSAM combined-preintegration parameters from Kalibr-style noise densities (the
    calibration's, or ``gyro_density`` / ``accel_density`` in their place)."""
    params = gtsam.PreintegrationCombinedParams.MakeSharedU(imu.gravity_m_s2)
    eye = np.eye(3)
    g_nd = imu.gyro_noise_density if gyro_density is None else gyro_density
    a_nd = imu.accel_noise_density if accel_density is None else accel_density
    params.setGyroscopeCovariance(g_nd**2 * eye)
    params.setAccelerometerCovariance(a_nd**2 * eye)
    params.setBiasOmegaCovariance(imu.gyro_random_walk**2 * eye)
    params.setBiasAccCovariance(imu.accel_random_walk**2 * eye)
    params.setIntegrationCovariance(1e-8 * eye)
    return params


def make_bias(gyro_rad_s: np.ndarray, accel_m_s2: np.ndarray) -> gtsam.imuBias.ConstantBias:
    """GTSAM bias object (its constructor takes accel first)."""
    return gtsam.imuBias.ConstantBias(
        np.asarray(accel_m_s2, dtype=float), np.asarray(gyro_rad_s, dtype=float)
    )


def bias_noise(sigma_accel_m_s2: float, sigma_gyro_rad_s: float) -> gtsam.noiseModel.Diagonal:
    """Diagonal noise on a ``ConstantBias`` (its tangent is accelerometer first, as
    :func:`make_bias`'s constructor)."""
    sa, sg = sigma_accel_m_s2, sigma_gyro_rad_s
    return gtsam.noiseModel.Diagonal.Sigmas(np.array([sa, sa, sa, sg, sg, sg]))


def pose_noise(sigma_rad: float, sigma_m: float) -> gtsam.noiseModel.Diagonal:
    """Diagonal noise on a ``Pose3`` (its tangent is rotation first, then translation)."""
    return gtsam.noiseModel.Diagonal.Sigmas(np.array([sigma_rad] * 3 + [sigma_m] * 3))


def integration_pieces(
    t_ns: np.ndarray,
    gyro_rad_s: np.ndarray,
    accel_m_s2: np.ndarray,
    t0_ns: int,
    t1_ns: int,
    max_gap_s: float,
) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """Pieces (dt_s (P,), gyro (P, 3), accel (P, 3)) covering [t0_ns, t1_ns] exactly.

    Returns None when the samples do not cover the interval or an interval between samples
    (including the distance from a keyframe time to the nearest sample outside it) is longer
    than ``max_gap_s``.
    """
    if t1_ns <= t0_ns or len(t_ns) == 0:
        return None
    i_first = int(np.searchsorted(t_ns, t0_ns, side="right")) - 1  # last sample <= t0
    i_last = int(np.searchsorted(t_ns, t1_ns, side="left"))  # first sample >= t1
    lo = max(i_first, 0)
    hi = min(i_last, len(t_ns) - 1)
    bracket = t_ns[lo : hi + 1]
    edges = np.concatenate(([min(t0_ns, bracket[0])], bracket, [max(t1_ns, bracket[-1])]))
    if np.diff(edges).max() * 1e-9 > max_gap_s:
        return None
    inner = (t_ns > t0_ns) & (t_ns < t1_ns)
    knots = np.concatenate(([t0_ns], t_ns[inner], [t1_ns])).astype(np.int64)
    t_rel = (t_ns - t0_ns).astype(np.float64)
    k_rel = (knots - t0_ns).astype(np.float64)
    g = np.stack([np.interp(k_rel, t_rel, gyro_rad_s[:, a]) for a in range(3)], axis=1)
    acc = np.stack([np.interp(k_rel, t_rel, accel_m_s2[:, a]) for a in range(3)], axis=1)
    dt_s = np.diff(knots).astype(np.float64) * 1e-9
    return dt_s, 0.5 * (g[:-1] + g[1:]), 0.5 * (acc[:-1] + acc[1:])


def integrate_pieces(
    pim: gtsam.PreintegratedCombinedMeasurements | gtsam.PreintegratedImuMeasurements,
    pieces: tuple[np.ndarray, np.ndarray, np.ndarray],
    midpoint_rotation: bool = False,
) -> None:
    """Feed pieces to a preintegrator (about 2 us per piece).

    ``midpoint_rotation``: each piece's specific force is first rotated by half the piece's
    rotation (``Exp(w dt / 2) a``), so that GTSAM's update, which rotates it into the
    preintegration frame by the rotation at the piece's *start*, applies the rotation at its
    middle (the midpoint rule, as ``imu_intrinsics.fit_intrinsics`` integrates). The start's
    rotation is off by ``w x a dt / 2`` on every piece, a systematic acceleration (gravity
    times a pitch or roll rate: 0.1 rad/s at 200 Hz makes 2.5 mm/s^2), as large as a
    monocular map's scale error times its acceleration (1 % of figure8's 0.15 m/s^2): exact
    synthetic readings and poses left the global adjustment's monocular scale 0.2-0.4 % off
    without it, under 0.04 % with it (BENCHMARKS.md, mono18h)."""
    dt_s, gyro, accel = pieces
    if midpoint_rotation and len(dt_s):
        half = so3_exp_batch(0.5 * np.asarray(gyro, float) * np.asarray(dt_s, float)[:, None])
        accel = np.einsum("nij,nj->ni", half, np.asarray(accel, float))
    for k in range(len(dt_s)):
        if dt_s[k] > 0.0:
            pim.integrateMeasurement(accel[k], gyro[k], float(dt_s[k]))


def backend_imu_buffer(imu: ImuCalibration, config: BackendConfig) -> ImuBuffer:
    """The back end's IMU store: kept until trimmed, saturated samples rejected, gaps longer
    than ``imu_gap_warn_factor`` nominal periods counted, every problem logged."""
    nominal_dt_ns = int(round(1e9 / imu.rate_hz))
    return ImuBuffer(
        keep_ns=None,
        max_gyro_rad_s=config.max_gyro_rad_s,
        max_accel_m_s2=config.max_accel_m_s2,
        gap_warn_ns=config.imu_gap_warn_factor * nominal_dt_ns,
        log_problems=True,
    )


def preintegrate(
    buffer: ImuBuffer,
    params: gtsam.PreintegrationCombinedParams,
    bias: gtsam.imuBias.ConstantBias,
    t0_ns: int,
    t1_ns: int,
    max_gap_s: float,
    imu: ImuCalibration | None = None,
    scale_error: tuple[float, float] | None = None,
    accel_error_of_deviation: bool = False,
    accel_density_factor: float = 1.0,
) -> gtsam.PreintegratedCombinedMeasurements | None:
    """Preintegrated measurements between two keyframe times, or None (no IMU factor) when the
    buffer does not cover [t0_ns, t1_ns] or a gap in it is longer than ``max_gap_s``.

    ``scale_error`` (gyro, accel; fractions) with the calibration ``imu``: the noise of this
    interval allows for that much scale / axis error (:func:`scale_error_params`) instead of
    ``params``' fixed densities (the accelerometer's calibrated density times
    ``accel_density_factor`` there)."""
    t, g, a = buffer.arrays()
    pieces = integration_pieces(t, g, a, t0_ns, t1_ns, max_gap_s)
    if pieces is None:
        return None
    if imu is not None and scale_error is not None and max(scale_error) > 0:
        params = scale_error_params(
            imu,
            pieces,
            scale_error[0],
            scale_error[1],
            accel_error_of_deviation,
            accel_density_factor,
        )
    pim = gtsam.PreintegratedCombinedMeasurements(params, bias)
    integrate_pieces(pim, pieces)
    return pim


def scale_error_params(
    imu: ImuCalibration,
    pieces: tuple[np.ndarray, np.ndarray, np.ndarray],
    gyro_scale_error: float,
    accel_scale_error: float,
    accel_error_of_deviation: bool = False,
    accel_density_factor: float = 1.0,
) -> gtsam.PreintegrationCombinedParams:
    """Preintegration parameters for one interval whose white noise also covers a scale (or
    axis) error of the sensors, a systematic error proportional to what they read.

    Why: a real IMU's gyro and accelerometer scale factors are off by a few tenths of a percent
    (0.3 % std in ``slam synth --camera realistic``). On a fast rotation (3 rad/s) that is an
    error of 0.01-0.02 rad/s, 60-120x the EuRoC gyro's white noise over a keyframe interval,
    and a back end that trusts the calibration's densities bends the trajectory to it (8 s of
    ``aggressive`` with 0.3 % scale errors: live ATE 19.6 mm instead of 2.9). An error ``s``
    times the reading ``w`` accumulates ``s |w| T`` over an interval ``T``; white noise of
    density ``q`` accumulates ``q sqrt(T)``. Equal at ``q = s * mean|w| * sqrt(T)``, added in
    quadrature to the calibration's density (the accelerometer's against its reading less
    nothing: gravity is part of what it reads). Intervals without motion keep the calibration's
    densities, so a still or slow IMU is trusted as before.

    ``accel_error_of_deviation``: the accelerometer's term grows with the reading's deviation
    from its mean over the interval instead of the whole reading. The constant part (mostly
    gravity: 0.5 % of it is 0.05 m/s^2, on every interval, still or not) is an offset over
    the interval, which the bias state takes (used by the monocular preset, where the
    whole-reading term left the scale to the visual factors; BENCHMARKS.md).

    ``accel_density_factor``: the calibration's accelerometer density is first multiplied by
    this (the monocular preset's 3: with the deviation's term, an interval of constant specific
    force kept the bare calibrated density, and the monocular window's elimination met
    "Indeterminate linear system" on the hall; BENCHMARKS.md).
    """
    dt_s, gyro, accel = pieces
    span_s = float(dt_s.sum())
    if span_s <= 0.0:
        return preintegration_params(imu)
    mean_rate = float(np.sum(np.linalg.norm(gyro, axis=1) * dt_s) / span_s)
    if accel_error_of_deviation:
        mean_vec = np.sum(accel * dt_s[:, None], axis=0) / span_s
        mean_accel = float(np.sum(np.linalg.norm(accel - mean_vec, axis=1) * dt_s) / span_s)
    else:
        mean_accel = float(np.sum(np.linalg.norm(accel, axis=1) * dt_s) / span_s)
    root_t = np.sqrt(span_s)
    g_nd = np.hypot(imu.gyro_noise_density, gyro_scale_error * mean_rate * root_t)
    a_nd = np.hypot(
        imu.accel_noise_density * accel_density_factor, accel_scale_error * mean_accel * root_t
    )
    return preintegration_params(imu, float(g_nd), float(a_nd))

"""Does a real IMU stream agree with the trajectory the images are rendered along?

`slam synth --from-trajectory FILE --imu-csv IMU` renders the images along FILE's poses and
plays the real IMU that flew the real path. Where FILE's orientation is off from the motion the
IMU measured, the images and the gyro disagree, and every visual-inertial estimate pays for it:
EuRoC's original V1_01 ground truth (``state_groundtruth_estimate0``) has orientation errors of a
degree or more (OpenVINS recomputed it with vicon2gt for that reason); rendered from it, the gyro
integrated over 5 s differs from the rendered rotation by 1.6 deg (median; 3.9 max), from
OpenVINS's recomputed one by 0.3 deg, and the same code's odometry ATE was 90 mm against 16 mm
(BENCHMARKS.md, "The V1_01 sequence").

:func:`gyro_agreement` integrates the gyro, less its mean residual (a constant bias), over
consecutive windows and compares each window's rotation with the trajectory's.

:func:`accel_scale_agreement` reads the accelerometer's scale against the trajectory's positions:
``p(t+T) - 2 p(t) + p(t-T)`` is exactly the triangle-weighted integral of the world acceleration
over ``[t-T, t+T]``, so it needs no velocity and no spline derivative. The real V1_01 IMU against
OpenVINS's ground truth, with vicon2gt's (the ground truth's) accelerometer bias taken out, reads
1.008 (its accelerations 0.8 % smaller than the positions'), with 7 mm rms left; with a bias of
its own, linear between knots 10 s apart, 1.000 with 20 mm left: its error against that truth
wanders faster than a bias does (BENCHMARKS.md, "branch v101imu18"). That disagreement is the
data's own, and a monocular scale taken from that IMU pays for it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from datasets.sequence import ImuArrays
from datasets.synth.trajectories import Motion
from slam.core.geometry import rotation_angle_rad, so3_exp_batch

WINDOW_S = 5.0
ACCEL_SPAN_S = 1.0
ACCEL_KNOT_S = 10.0
MAX_MEDIAN_DISAGREEMENT_DEG = 0.8
"""Above this median per 5 s window, ``slam synth`` warns: the images and the IMU describe
different rotations (a consistent pair with the real V1_01 IMU measured 0.32 deg; ADIS16448
noise alone gives ~0.05 deg)."""


@dataclass(frozen=True)
class GyroAgreement:
    """Per window of ``window_s``: the angle (deg) between the bias-corrected gyro's rotation
    and the trajectory's; ``gyro_bias_rad_s`` the constant bias that was removed."""

    window_s: float
    disagreement_deg: np.ndarray
    gyro_bias_rad_s: np.ndarray

    @property
    def median_deg(self) -> float:
        return float(np.median(self.disagreement_deg))

    @property
    def max_deg(self) -> float:
        return float(np.max(self.disagreement_deg))


def gyro_agreement(
    motion: Motion, imu: ImuArrays, motion_t0_ns: int, window_s: float = WINDOW_S
) -> GyroAgreement | None:
    """Compare ``imu``'s gyro with ``motion`` (evaluated at ``(t_ns - motion_t0_ns)`` s) over
    consecutive windows inside the motion's span; None when not one window fits."""
    t_rel = (np.asarray(imu.t_ns, np.int64) - int(motion_t0_ns)).astype(np.float64) * 1e-9
    inside = (t_rel >= motion.t_start_s) & (t_rel <= motion.t_end_s)
    t_s, gyro = t_rel[inside], np.asarray(imu.gyro_rad_s, np.float64)[inside]
    if len(t_s) < 3 or t_s[-1] - t_s[0] < window_s:
        return None
    samples = motion.sample(t_s)
    bias = np.mean(gyro - samples.omega_body_rad_s, axis=0)
    mid = 0.5 * (gyro[:-1] + gyro[1:]) - bias  # sample k to k + 1 (trapezoidal)
    steps = so3_exp_batch(mid * np.diff(t_s)[:, None])
    rot = samples.world_from_body_rot
    angles = []
    start = 0
    while True:
        end = int(np.searchsorted(t_s, t_s[start] + window_s))
        if end >= len(t_s):
            break
        integrated = np.eye(3)
        for step in steps[start:end]:
            integrated = integrated @ step
        truth = rot[start].T @ rot[end]
        angles.append(np.degrees(rotation_angle_rad(truth.T @ integrated)))
        start = end
    return GyroAgreement(window_s, np.asarray(angles), bias)


@dataclass(frozen=True)
class AccelScale:
    """The accelerometer against the trajectory: ``scale`` multiplies the IMU's world
    accelerations to give the trajectory's (1: they agree; 0.97: the IMU reads 3 % large);
    ``world_offset_m_s2`` a constant world-frame acceleration left over (gravity's direction in
    the trajectory's world off the -z the IMU is integrated with); ``rms_residual_m`` of the
    second differences; ``count`` of them."""

    scale: float
    world_offset_m_s2: np.ndarray
    rms_residual_m: float
    count: int


def _double_integral(t_s: np.ndarray, accel: np.ndarray) -> np.ndarray:
    """Position from acceleration samples (N, ...) at times ``t_s`` (zero initial state):
    trapezoidal velocity, then position with the linear-acceleration correction, so that a
    piecewise-linear acceleration is integrated exactly."""
    dt = np.diff(t_s).reshape((-1,) + (1,) * (accel.ndim - 1))
    zero = np.zeros((1,) + accel.shape[1:])
    vel = np.concatenate([zero, np.cumsum(0.5 * (accel[1:] + accel[:-1]) * dt, axis=0)])
    step = 0.5 * (vel[1:] + vel[:-1]) * dt - (accel[1:] - accel[:-1]) * dt**2 / 12.0
    return np.concatenate([zero, np.cumsum(step, axis=0)])


def accel_scale_agreement(
    motion: Motion,
    imu: ImuArrays,
    motion_t0_ns: int,
    gravity_m_s2: float,
    span_s: float = ACCEL_SPAN_S,
    knot_s: float = ACCEL_KNOT_S,
) -> AccelScale | None:
    """Fit ``D2p = s D2(R a + g) - D2(R b(t)) + c T^2`` over second differences of span
    ``span_s`` centred every 50 ms: ``R`` the trajectory's orientation at the IMU's times, ``a``
    the accelerometer, ``b(t)`` a body-frame bias linear between knots ``knot_s`` apart (the
    real bias drifts), ``c`` one world offset. None when fewer than four centres fit."""
    t_rel = (np.asarray(imu.t_ns, np.int64) - int(motion_t0_ns)).astype(np.float64) * 1e-9
    inside = (t_rel >= motion.t_start_s) & (t_rel <= motion.t_end_s)
    t_s, accel = t_rel[inside], np.asarray(imu.accel_m_s2, np.float64)[inside]
    if len(t_s) < 3:
        return None
    centres = np.arange(t_s[0] + span_s, t_s[-1] - span_s, 0.05)
    if len(centres) < 4:
        return None
    rot = motion.sample(t_s).world_from_body_rot
    gravity = np.array([0.0, 0.0, -gravity_m_s2])
    pos_meas = _double_integral(t_s, np.einsum("nij,nj->ni", rot, accel) + gravity)
    # a unit bias on body axis j weighted by knot k's hat function, in the world: (N, 3, 3, K)
    knots = np.arange(t_s[0], t_s[-1] + knot_s, knot_s)
    hats = np.clip(1.0 - np.abs(t_s[:, None] - knots[None, :]) / knot_s, 0.0, None)
    pos_bias = _double_integral(t_s, rot[:, :, :, None] * hats[:, None, None, :])

    def second_difference(values: np.ndarray) -> np.ndarray:
        flat = values.reshape(len(t_s), -1)
        at = [
            np.stack([np.interp(centres + d, t_s, col) for col in flat.T], axis=1)
            for d in (-span_s, 0.0, span_s)
        ]
        return (at[2] - 2.0 * at[1] + at[0]).reshape((len(centres),) + values.shape[1:])

    truth = motion.sample(np.concatenate([centres - span_s, centres, centres + span_s]))
    p = truth.positions_m.reshape(3, len(centres), 3)
    n = len(centres)
    rows = np.concatenate(
        [
            second_difference(pos_meas)[:, :, None],
            np.broadcast_to(np.eye(3) * span_s**2, (n, 3, 3)),
            second_difference(pos_bias).reshape(n, 3, -1),
        ],
        axis=2,
    ).reshape(3 * n, -1)
    target = (p[2] - 2.0 * p[1] + p[0]).reshape(3 * n)
    sol, *_ = np.linalg.lstsq(rows, target, rcond=None)
    resid = target - rows @ sol
    return AccelScale(
        scale=float(sol[0]),
        world_offset_m_s2=sol[1:4].copy(),
        rms_residual_m=float(np.sqrt(np.mean(resid**2))),
        count=n,
    )

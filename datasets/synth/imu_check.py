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
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from datasets.sequence import ImuArrays
from datasets.synth.trajectories import Motion
from slam.core.geometry import rotation_angle_rad, so3_exp_batch

WINDOW_S = 5.0
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

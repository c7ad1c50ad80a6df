"""IMU simulator: exact before noise (integrates back to ground truth), still start, noise
levels, determinism by seed."""

from __future__ import annotations

import numpy as np
import pytest

from datasets.synth.imu_sim import exact_imu, simulate_imu
from datasets.synth.trajectories import TimeWarp, make_profile
from slam.core.calibration import ImuCalibration
from slam.core.geometry import so3_exp, so3_log

G = 9.81


def _integrate(motion, t0_s: float, t1_s: float, rate_hz: float = 200.0):
    """Trapezoidal strapdown integration of the simulated 200 Hz IMU from the true state at
    t0_s; returns (true end state, integrated end state)."""
    calib = ImuCalibration(rate_hz=rate_hz)
    n = int(round((t1_s - t0_s) * rate_hz)) + 1
    t_ns = np.arange(n, dtype=np.int64) * int(1e9 / rate_hz)
    imu = simulate_imu(motion, t_ns, t0_s, calib, noise=False).arrays
    truth = motion.sample(np.array([t0_s, t0_s + (n - 1) / rate_hz]))
    rot = truth.world_from_body_rot[0].copy()
    vel = truth.velocities_m_s[0].copy()
    pos = truth.positions_m[0].copy()
    g = np.array([0.0, 0.0, -G])
    dt = 1.0 / rate_hz
    for k in range(n - 1):
        rot_next = rot @ so3_exp(0.5 * (imu.gyro_rad_s[k] + imu.gyro_rad_s[k + 1]) * dt)
        a0 = rot @ imu.accel_m_s2[k] + g
        a1 = rot_next @ imu.accel_m_s2[k + 1] + g
        pos = pos + vel * dt + (2 * a0 + a1) / 6 * dt * dt
        vel = vel + 0.5 * (a0 + a1) * dt
        rot = rot_next
    return truth, (rot, vel, pos)


@pytest.mark.parametrize(
    ("profile", "pos_tol_m", "rot_tol_rad"),
    [("figure8", 2e-4, 2e-6), ("hall", 2e-4, 2e-6), ("aggressive", 2e-2, 2e-4)],
)
def test_noiseless_imu_integrates_back_to_ground_truth(
    profile: str, pos_tol_m: float, rot_tol_rad: float
) -> None:
    motion = make_profile(profile)
    truth, (rot, vel, pos) = _integrate(motion, 1.0, 11.0)  # through the start ramp, 10 s
    rot_err = np.linalg.norm(so3_log(truth.world_from_body_rot[1].T @ rot))
    pos_err = np.linalg.norm(pos - truth.positions_m[1])
    assert rot_err < rot_tol_rad, rot_err
    assert pos_err < pos_tol_m, pos_err
    assert np.linalg.norm(vel - truth.velocities_m_s[1]) < pos_tol_m


def test_still_start_is_still_and_reads_gravity() -> None:
    motion = make_profile("figure8")
    t = np.arange(0.0, 2.0, 0.005)
    gyro, accel = exact_imu(motion, t, G)
    ms = motion.sample(t)
    assert np.all(gyro == 0.0)
    assert np.ptp(ms.positions_m, axis=0).max() == 0.0
    assert np.allclose(np.linalg.norm(accel, axis=1), G, atol=1e-12)
    assert np.all(np.ptp(accel, axis=0) < 1e-12)
    # EuRoC-like mounting: body x is up
    assert accel[0, 0] > 0.9 * G
    # and it really moves afterwards
    assert np.linalg.norm(motion.sample(np.array([6.0])).velocities_m_s) > 0.1
    moving = make_profile("figure8", moving_start=True)
    assert np.linalg.norm(moving.sample(np.array([0.0])).velocities_m_s) > 0.1


def test_time_warp_is_smooth() -> None:
    warp = TimeWarp(2.0, 2.0)
    t = np.linspace(1.5, 4.5, 30001)
    s, sd, sdd = warp.eval(t)
    dt = t[1] - t[0]
    assert np.max(np.abs(np.gradient(s, dt) - sd)) < 1e-6
    assert np.max(np.abs(np.gradient(sd, dt) - sdd)) < 1e-5
    assert np.max(np.abs(np.diff(sdd))) < 1e-3  # continuous second derivative


def test_noise_levels_and_bias_walk_follow_the_calibration() -> None:
    motion = make_profile("figure8")
    calib = ImuCalibration()
    t_ns = np.arange(40000, dtype=np.int64) * 5_000_000
    clean = simulate_imu(motion, t_ns, 0.0, calib, noise=False).arrays
    noisy = simulate_imu(motion, t_ns, 0.0, calib, noise=True, seed=3)
    white_g = noisy.arrays.gyro_rad_s - clean.gyro_rad_s - noisy.gyro_bias_rad_s
    white_a = noisy.arrays.accel_m_s2 - clean.accel_m_s2 - noisy.accel_bias_m_s2
    dt = 1.0 / calib.rate_hz
    assert np.allclose(white_g.std(axis=0), calib.gyro_noise_density / np.sqrt(dt), rtol=0.03)
    assert np.allclose(white_a.std(axis=0), calib.accel_noise_density / np.sqrt(dt), rtol=0.03)
    steps = np.diff(noisy.gyro_bias_rad_s, axis=0)
    assert np.allclose(steps.std(axis=0), calib.gyro_random_walk * np.sqrt(dt), rtol=0.03)
    steps_a = np.diff(noisy.accel_bias_m_s2, axis=0)
    assert np.allclose(steps_a.std(axis=0), calib.accel_random_walk * np.sqrt(dt), rtol=0.03)


def test_imu_is_deterministic_by_seed() -> None:
    motion = make_profile("loop")
    calib = ImuCalibration()
    t_ns = np.arange(2000, dtype=np.int64) * 5_000_000
    a = simulate_imu(motion, t_ns, 0.0, calib, seed=7).arrays
    b = simulate_imu(motion, t_ns, 0.0, calib, seed=7).arrays
    c = simulate_imu(motion, t_ns, 0.0, calib, seed=8).arrays
    assert np.array_equal(a.gyro_rad_s, b.gyro_rad_s)
    assert np.array_equal(a.accel_m_s2, b.accel_m_s2)
    assert not np.array_equal(a.gyro_rad_s, c.gyro_rad_s)
    assert not np.array_equal(a.accel_m_s2, c.accel_m_s2)

"""IMU preintegration against EuRoC V1_01 ground truth, and IMU sanitising."""

from __future__ import annotations

import logging

import gtsam
import numpy as np
import pytest

from slam.backend.config import BackendConfig
from slam.backend.imu import (
    backend_imu_buffer,
    integrate_pieces,
    integration_pieces,
    make_bias,
    preintegrate,
    preintegration_params,
)
from slam.core.calibration import ImuCalibration
from slam.core.geometry import quat_wxyz_to_matrix, so3_log
from slam.core.messages import ImuSample


def test_preintegration_matches_ground_truth_over_half_second_windows(euroc_micro_imu_gt):
    imu, gt = euroc_micro_imu_gt
    t_ns = imu[:, 0].astype(np.int64)
    gyro, accel = imu[:, 1:4], imu[:, 4:7]
    t_gt = gt[:, 0].astype(np.int64)
    params = preintegration_params(ImuCalibration())
    pos_err, rot_err_deg = [], []
    for i in range(0, len(gt) - 10, 5):  # 0.5 s windows (GT at 20 Hz), start every 0.25 s
        j = i + 10
        bias = make_bias(gt[i, 11:14], gt[i, 14:17])
        pim = gtsam.PreintegratedCombinedMeasurements(params, bias)
        pieces = integration_pieces(t_ns, gyro, accel, int(t_gt[i]), int(t_gt[j]), 0.1)
        assert pieces is not None
        assert abs(pieces[0].sum() - (t_gt[j] - t_gt[i]) * 1e-9) < 1e-9
        integrate_pieces(pim, pieces)
        rot_i = quat_wxyz_to_matrix(gt[i, 4:8])
        rot_j = quat_wxyz_to_matrix(gt[j, 4:8])
        pred = pim.predict(gtsam.NavState(gtsam.Rot3(rot_i), gt[i, 1:4], gt[i, 8:11]), bias)
        pos_err.append(np.linalg.norm(pred.position() - gt[j, 1:4]))
        rot_err_deg.append(np.degrees(np.linalg.norm(so3_log(rot_j.T @ pred.attitude().matrix()))))
    pos_err = np.asarray(pos_err)
    rot_err_deg = np.asarray(rot_err_deg)
    assert len(pos_err) > 500  # the whole 145 s flight
    # measured: position median 6.1 mm, p90 8.7 mm, max 12 mm; rotation median 0.058 deg, max 0.18
    assert np.median(pos_err) < 0.01
    assert np.percentile(pos_err, 90) < 0.015
    assert pos_err.max() < 0.025
    assert np.median(rot_err_deg) < 0.1
    assert rot_err_deg.max() < 0.3


def test_pieces_split_boundary_intervals_exactly():
    t_ns = np.arange(0, 100_000_000, 5_000_000, dtype=np.int64)  # 200 Hz
    gyro = np.tile([0.1, -0.2, 0.3], (len(t_ns), 1))
    accel = np.column_stack([np.linspace(0, 1, len(t_ns))] * 3)
    a, b, c = 7_300_000, 31_100_000, 77_700_000
    whole = integration_pieces(t_ns, gyro, accel, a, c, 0.1)
    first = integration_pieces(t_ns, gyro, accel, a, b, 0.1)
    second = integration_pieces(t_ns, gyro, accel, b, c, 0.1)
    assert whole is not None and first is not None and second is not None
    assert whole[0].sum() == pytest.approx((c - a) * 1e-9, abs=1e-12)
    # trapezoidal accel integral of a linear signal is exact, and splitting does not change it
    integral = lambda p: (p[0][:, None] * p[2]).sum(axis=0)  # noqa: E731
    np.testing.assert_allclose(integral(first) + integral(second), integral(whole), atol=1e-12)
    t_s = t_ns * 1e-9
    slope = 1.0 / (t_s[-1] - t_s[0])
    exact = 0.5 * slope * ((c * 1e-9) ** 2 - (a * 1e-9) ** 2)
    assert integral(whole)[0] == pytest.approx(exact, rel=1e-9)


def test_gap_longer_than_limit_gives_no_preintegration():
    t_ns = np.concatenate(
        [np.arange(0, 1_000_000_000, 5_000_000), np.arange(1_500_000_000, 2_000_000_000, 5_000_000)]
    ).astype(np.int64)
    z = np.zeros((len(t_ns), 3))
    assert integration_pieces(t_ns, z, z, 100_000_000, 900_000_000, 0.1) is not None
    assert integration_pieces(t_ns, z, z, 900_000_000, 1_600_000_000, 0.1) is None
    assert integration_pieces(t_ns, z, z, 1_600_000_000, 1_900_000_000, 0.1) is not None
    assert integration_pieces(t_ns, z, z, 1_900_000_000, 2_500_000_000, 0.1) is None  # not covered


def test_buffer_rejects_counts_and_warns(caplog):
    buf = backend_imu_buffer(ImuCalibration(), BackendConfig())
    good = lambda t: ImuSample(t, np.array([0.01, 0.0, 0.0]), np.array([0.0, 0.0, 9.81]))  # noqa: E731
    with caplog.at_level(logging.WARNING):
        assert buf.add(good(0))
        assert not buf.add(ImuSample(5_000_000, np.array([np.nan, 0, 0]), np.zeros(3)))
        assert not buf.add(ImuSample(10_000_000, np.zeros(3), np.array([0, np.inf, 0])))
        assert not buf.add(ImuSample(15_000_000, np.zeros(3), np.array([0, 0, 200.0])))  # > 16 g
        assert not buf.add(ImuSample(20_000_000, np.array([0, 40.0, 0]), np.zeros(3)))  # > 35 rad/s
        assert buf.add(good(25_000_000))
        assert not buf.add(good(25_000_000))  # duplicate time
        assert buf.add(good(525_000_000))  # a 0.5 s gap: accepted but warned
    s = buf.stats
    assert (s.accepted, s.rejected_nonfinite, s.rejected_saturated, s.rejected_out_of_order) == (
        3,
        2,
        2,
        1,
    )
    assert s.gaps_warned == 2  # the rejected samples left a 25 ms hole, then the 0.5 s gap
    assert s.rejected == 5
    text = caplog.text
    assert "non-finite" in text and "saturated" in text and "gap" in text
    # the gap blocks preintegration across it, but not before it
    params = preintegration_params(ImuCalibration())
    bias = make_bias(np.zeros(3), np.zeros(3))
    max_gap_s = BackendConfig().imu_gap_max_s
    assert preintegrate(buf, params, bias, 0, 25_000_000, max_gap_s) is not None
    assert preintegrate(buf, params, bias, 20_000_000, 500_000_000, max_gap_s) is None
    buf.trim(400_000_000)
    assert len(buf) == 2  # the last sample before the trim time is kept for bracketing


def test_dead_reckoning_follows_the_simulated_truth():
    """The front end's IMU pose prior (sample-and-hold dead reckoning) over 0.2 s of flight."""
    from datasets.synth.vio_world import generate_world
    from slam.core.messages import ImuBatch
    from slam.imu_buffer import ImuBuffer, propagate_pose

    world = generate_world(duration_s=3.0, seed=1, imu_noise=False, landmarks_per_keyframe=10)
    imu = world.imu.arrays
    buf = ImuBuffer(keep_ns=None)
    buf.extend(ImuBatch(imu.t_ns, imu.gyro_rad_s, imu.accel_m_s2).samples())
    kf0, kf1 = world.keyframes[5], world.keyframes[7]  # 0.2 s apart
    t0_s = (kf0.t_ns - 1_000_000_000) * 1e-9
    out = propagate_pose(
        buf.window(kf0.t_ns, kf1.t_ns),
        kf0.t_ns,
        kf1.t_ns,
        world.world_from_body_gt[5],
        world.trajectory.sample(np.array([t0_s])).velocities_m_s[0],
        world.imu.gyro_bias_rad_s[0],
        world.imu.accel_bias_m_s2[0],
        world.calibration.imu.gravity_m_s2,
    )
    assert out is not None
    pose, _ = out
    assert np.linalg.norm(pose[:3, 3] - world.world_from_body_gt[7][:3, 3]) < 1e-3  # 0.06 mm
    t_end = int(imu.t_ns[-1]) + 10**9
    assert (
        propagate_pose(buf.window(kf1.t_ns, t_end), kf1.t_ns, t_end, pose, *np.zeros((3, 3)))
        is None
    )  # not covered


def test_scale_error_noise_covers_a_gyro_scale_error():
    """0.5 % gyro scale error on a 3 rad/s turn over 0.2 s: the rotation it puts into the
    preintegration is ~30 sigma off under the calibration's noise, within ~1 sigma under the
    scale-error model; a still interval keeps the calibration's noise."""
    from slam.backend.imu import scale_error_params

    imu = ImuCalibration()
    dt, n = 0.005, 40
    rate = np.array([0.0, 0.0, 3.0])
    t_ns = np.arange(n + 1) * 5_000_000
    gyro = np.tile(rate * 1.005, (n + 1, 1))
    accel = np.tile([0.0, 0.0, 9.81], (n + 1, 1))
    pieces = integration_pieces(t_ns, gyro, accel, 0, int(t_ns[-1]), 0.1)
    assert pieces is not None
    bias = make_bias(np.zeros(3), np.zeros(3))

    def rotation_sigmas(params: gtsam.PreintegrationCombinedParams) -> float:
        pim = gtsam.PreintegratedCombinedMeasurements(params, bias)
        integrate_pieces(pim, pieces)
        err = pim.deltaRij().localCoordinates(gtsam.Rot3.Rz(3.0 * n * dt))
        cov = pim.preintMeasCov()[:3, :3]  # rotation first
        return float(np.sqrt(err @ np.linalg.solve(cov, err)))

    assert rotation_sigmas(preintegration_params(imu)) > 20.0
    assert rotation_sigmas(scale_error_params(imu, pieces, 0.005, 0.005)) < 1.5
    still = integration_pieces(t_ns, np.zeros((n + 1, 3)), accel, 0, int(t_ns[-1]), 0.1)
    assert still is not None
    p_still = scale_error_params(imu, still, 0.005, 0.0)
    np.testing.assert_allclose(
        p_still.getGyroscopeCovariance(), preintegration_params(imu).getGyroscopeCovariance()
    )


def test_accel_density_factor_scales_the_calibrated_accelerometer_noise():
    """Under ``accel_error_of_deviation`` a constant specific force adds nothing to the
    accelerometer's noise: the density is the calibration's times ``accel_density_factor``
    (the monocular preset's 3), and a factor of 1 leaves the calibration's exactly."""
    from slam.backend.imu import scale_error_params
    from slam.config import preset_config

    imu = ImuCalibration()
    n = 40
    t_ns = np.arange(n + 1) * 5_000_000
    gyro = np.tile([0.0, 0.0, 0.5], (n + 1, 1))
    accel = np.tile([0.3, -0.2, 9.81], (n + 1, 1))
    pieces = integration_pieces(t_ns, gyro, accel, 0, int(t_ns[-1]), 0.1)
    assert pieces is not None
    base = preintegration_params(imu).getAccelerometerCovariance()
    one = scale_error_params(imu, pieces, 0.005, 0.005, True, 1.0)
    np.testing.assert_array_equal(one.getAccelerometerCovariance(), base)
    factor = preset_config("euroc-mono-imu").backend.imu_accel_density_factor
    assert factor == 3.0
    two = scale_error_params(imu, pieces, 0.005, 0.005, True, factor)
    np.testing.assert_allclose(two.getAccelerometerCovariance(), base * factor**2, rtol=1e-12)
    # the gyro's noise is not touched by it
    np.testing.assert_array_equal(two.getGyroscopeCovariance(), one.getGyroscopeCovariance())

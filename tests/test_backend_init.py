"""Still-start initialisation on real EuRoC data, moving-start alignment on a simulated flight."""

from __future__ import annotations

import numpy as np
import pytest
from conftest import pose_keyframe

from datasets.synth.vio_world import generate_world
from slam.backend.config import BackendConfig
from slam.backend.init import (
    find_still_prefix,
    minimal_rotation,
    moving_init,
    still_init_align,
    still_init_kalman,
    world_from_vo_gravity,
)
from slam.core.calibration import ImuCalibration
from slam.core.geometry import quat_wxyz_to_matrix, so3_log, transform_points


def _angle_deg(a: np.ndarray, b: np.ndarray) -> float:
    c = float(a @ b / (np.linalg.norm(a) * np.linalg.norm(b)))
    return float(np.degrees(np.arccos(np.clip(c, -1.0, 1.0))))


def test_still_interval_detected_on_euroc(euroc_micro_imu_gt):
    imu, gt = euroc_micro_imu_gt
    t_ns = imu[:, 0].astype(np.int64)
    n = find_still_prefix(t_ns, imu[:, 1:4], imu[:, 4:7], BackendConfig())
    still_s = (t_ns[n - 1] - t_ns[0]) * 1e-9
    # ground truth: speed < 2 cm/s for the first ~5 s, then the MAV takes off (0.4 m/s at 5.5 s)
    speed = np.linalg.norm(gt[:, 8:11], axis=1)
    t_gt_s = (gt[:, 0] - gt[0, 0]) * 1e-9
    assert speed[t_gt_s < still_s].max() < 0.02
    assert 3.0 <= still_s <= 6.0


@pytest.mark.parametrize("method", ["kalman", "align"])
def test_static_init_on_euroc_gravity_and_gyro_bias(euroc_micro_imu_gt, method):
    imu, gt = euroc_micro_imu_gt
    t_ns = imu[:, 0].astype(np.int64)
    n = find_still_prefix(t_ns, imu[:, 1:4], imu[:, 4:7], BackendConfig())
    gyro, accel = imu[:n, 1:4], imu[:n, 4:7]
    if method == "kalman":
        res = still_init_kalman(gyro, accel, ImuCalibration())
    else:
        res = still_init_align(gyro, accel)
    up_body_gt = quat_wxyz_to_matrix(gt[0, 4:8]).T @ np.array([0.0, 0.0, 1.0])
    # measured (both methods agree to 0.01 deg): 0.60 deg (accel bias ~0.07 m/s^2 tilts it),
    # gyro bias error 0.001 rad/s
    assert _angle_deg(res.up_body, up_body_gt) < 1.0
    assert np.abs(res.bias_gyro_rad_s - gt[0, 11:14]).max() < 0.003
    rot = res.world_from_body_rotation()
    np.testing.assert_allclose(rot @ res.up_body, [0, 0, 1], atol=1e-9)


def test_minimal_rotation_and_world_from_vo():
    rng = np.random.default_rng(4)
    for _ in range(5):
        a, b = rng.normal(size=3), rng.normal(size=3)
        r = minimal_rotation(a, b)
        np.testing.assert_allclose(r @ (a / np.linalg.norm(a)), b / np.linalg.norm(b), atol=1e-9)
        np.testing.assert_allclose(r.T @ r, np.eye(3), atol=1e-12)
    origin = np.array([1.0, 2.0, 3.0])
    w_from_vo = world_from_vo_gravity(np.array([0.0, -1.0, 0.0]), origin)
    np.testing.assert_allclose(w_from_vo[:3, :3] @ [0, -1, 0], [0, 0, 1], atol=1e-12)
    np.testing.assert_allclose(transform_points(w_from_vo, origin[None]), origin[None], atol=1e-12)


@pytest.mark.parametrize("seed", [2, 5])
def test_moving_start_alignment_on_simulated_flight(seed):
    world = generate_world(duration_s=4.0, seed=seed, start_s=3.0 + seed)
    kfs = world.keyframes[:16]  # 1.5 s at 10 Hz, in motion from the first sample
    res = moving_init(
        np.array([k.t_ns for k in kfs]),
        np.array([k.world_from_body_vo for k in kfs]),
        world.imu.arrays.t_ns,
        world.imu.arrays.gyro_rad_s,
        world.imu.arrays.accel_m_s2,
        world.calibration.imu,
        BackendConfig(),
    )
    assert res is not None
    rot_vo_from_world = world.vo_from_world[:3, :3]
    gravity_vo_true = rot_vo_from_world @ np.array([0.0, 0.0, -9.81])
    assert _angle_deg(res.gravity_vo_m_s2, gravity_vo_true) < 1.5
    assert abs(res.gravity_norm_unconstrained_m_s2 - 9.81) < 0.2
    t_s = np.array([(k.t_ns - 1_000_000_000) * 1e-9 for k in kfs])
    v_true = world.trajectory.sample(t_s).velocities_m_s @ rot_vo_from_world.T
    speed = np.linalg.norm(v_true, axis=1)
    assert speed.min() > 0.3  # really a moving start
    assert np.linalg.norm(res.velocities_vo_m_s - v_true, axis=1).max() < 0.05
    assert np.abs(res.bias_gyro_rad_s - world.imu.gyro_bias_rad_s[0]).max() < 0.005


def test_backend_still_start_on_real_euroc_imu(euroc_micro_imu_gt):
    """The whole back end on the real stream: keyframes carry ground-truth poses as 'VO' (in the
    gravity-aligned Vicon frame) and no observations; it must initialise from the still start."""
    from datasets.rigs import euroc_like_calibration
    from slam.backend.smoother import VioBackend
    from slam.core.messages import ImuSample

    imu, gt = euroc_micro_imu_gt
    calib = euroc_like_calibration(distortion=False)
    backend = VioBackend(calib, BackendConfig(still_init_method="align"))
    t_imu = imu[:, 0].astype(np.int64)
    j = 0
    estimates = []
    for row in range(5, 80, 5):  # keyframes every 0.25 s over the first 4 s (still)
        t_kf = int(gt[row, 0])
        while j < len(t_imu) and t_imu[j] <= t_kf:
            backend.add_imu(ImuSample(int(t_imu[j]), imu[j, 1:4], imu[j, 4:7]))
            j += 1
        pose = np.eye(4)
        pose[:3, :3] = quat_wxyz_to_matrix(gt[row, 4:8])
        pose[:3, 3] = gt[row, 1:4]
        kf = pose_keyframe(t_kf, row, pose)
        estimates.append(backend.add_keyframe(kf))
    assert backend.stats.init_method == "still"
    assert all(e is not None for e in estimates)
    assert estimates[-1].initialized and not estimates[0].initialized
    # the Vicon frame is gravity aligned, so world_from_vo must be (nearly) a pure translation
    tilt_deg = np.degrees(np.linalg.norm(so3_log(backend.world_from_vo[:3, :3])))
    assert tilt_deg < 1.0
    assert np.abs(estimates[-1].bias_gyro_rad_s - gt[0, 11:14]).max() < 0.003
    assert len({e.keyframe_id for e in estimates}) == len(estimates)

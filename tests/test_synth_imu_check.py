"""A real IMU against the trajectory the images follow (``datasets.synth.imu_check``): a
consistent pair agrees to a fraction of the warning threshold whatever the gyro bias; a
trajectory whose orientation is off by a slowly varying tilt (as EuRoC's original V1_01
ground truth) is flagged, by the figure and by ``slam synth``'s warning."""

from __future__ import annotations

import numpy as np
import pytest
from conftest import require

from datasets.synth.generator import make_synthetic_sequence
from datasets.synth.imu_check import MAX_MEDIAN_DISAGREEMENT_DEG, gyro_agreement
from datasets.synth.imu_sim import read_imu_csv, simulate_imu
from datasets.synth.trajectories import SplineMotion, make_profile, motion_from_file
from slam.core.calibration import ImuCalibration
from slam.core.geometry import so3_exp
from slam.core.trajectory import Trajectory
from slam.evaluation.io import write_tum

T0_NS = 1_000_000_000_000
BIAS_RAD_S = np.array([0.01, -0.02, 0.005])


def _poses(duration_s: float, tilt_deg: float) -> tuple[np.ndarray, np.ndarray]:
    """A figure-8 sampled at 20 Hz (times s, world_from_body (N, 4, 4)), its orientation
    tilted about world x by ``tilt_deg * sin(2 pi t / 20 s)`` (0: the true motion)."""
    t = np.arange(0.0, duration_s, 0.05)
    s = make_profile("figure8").sample(t)
    poses = np.tile(np.eye(4), (len(t), 1, 1))
    tilt = np.radians(tilt_deg) * np.sin(2 * np.pi * t / 20.0)
    for k in range(len(t)):
        poses[k, :3, :3] = so3_exp(np.array([tilt[k], 0.0, 0.0])) @ s.world_from_body_rot[k]
    poses[:, :3, 3] = s.positions_m
    return t, poses


def _motion(t: np.ndarray, poses: np.ndarray) -> SplineMotion:
    traj = Trajectory.from_matrices(T0_NS + np.round(t * 1e9).astype(np.int64), poses)
    return SplineMotion(t0_ns=T0_NS, t_rel_s=t, positions_m=traj.positions_m, q_wxyz=traj.q_wxyz)


def _real_imu(duration_s: float):
    """The 'real' IMU: exact readings of the true motion plus a constant gyro bias."""
    true = _motion(*_poses(duration_s, 0.0))
    t_ns = T0_NS + np.arange(0, int(duration_s * 1e9) - 50_000_000, 5_000_000, dtype=np.int64)
    return simulate_imu(
        true, t_ns, 0.0, ImuCalibration(rate_hz=200.0), noise=False, gyro_bias0_rad_s=BIAS_RAD_S
    ).arrays


def test_consistent_pair_agrees_and_bias_is_recovered():
    imu = _real_imu(40.0)
    res = gyro_agreement(_motion(*_poses(40.0, 0.0)), imu, T0_NS)
    assert res is not None and len(res.disagreement_deg) == 7
    assert res.max_deg < 0.1 * MAX_MEDIAN_DISAGREEMENT_DEG
    np.testing.assert_allclose(res.gyro_bias_rad_s, BIAS_RAD_S, atol=2e-4)


def test_tilted_trajectory_is_flagged():
    imu = _real_imu(40.0)
    res = gyro_agreement(_motion(*_poses(40.0, 3.0)), imu, T0_NS)
    assert res is not None
    # a 3 deg tilt swinging with a 20 s period turns 0-4.2 deg within a 5 s window
    assert MAX_MEDIAN_DISAGREEMENT_DEG < res.median_deg < 4.3
    assert res.max_deg > 2.0


def test_too_short_for_a_window():
    imu = _real_imu(4.0)
    assert gyro_agreement(_motion(*_poses(4.0, 0.0)), imu, T0_NS) is None


@pytest.mark.parametrize("tilt_deg, warned", [(0.0, False), (3.0, True)])
def test_synth_warns_about_a_disagreeing_trajectory(tmp_path, tilt_deg, warned):
    duration_s = 12.0
    t, poses = _poses(duration_s, tilt_deg)
    traj_file = tmp_path / "gt.txt"
    write_tum(
        traj_file, Trajectory.from_matrices(T0_NS + np.round(t * 1e9).astype(np.int64), poses)
    )
    imu = _real_imu(duration_s)
    imu_file = tmp_path / "imu.csv"
    rows = np.column_stack([imu.gyro_rad_s, imu.accel_m_s2])
    imu_file.write_text(
        "#t,wx,wy,wz,ax,ay,az\n"
        + "".join(
            f"{t_ns}," + ",".join(f"{v:.9f}" for v in row) + "\n"
            for t_ns, row in zip(imu.t_ns.tolist(), rows, strict=True)
        )
    )
    seq = make_synthetic_sequence(trajectory_file=str(traj_file), imu_csv=str(imu_file))
    assert seq.gyro_agreement is not None
    assert any("IMU and the trajectory disagree" in w for w in seq.warnings) == warned


def test_euroc_v101_original_ground_truth_disagrees_with_its_imu(shared_data):
    """EuRoC's original V1_01 ground truth against the real IMU: flagged; OpenVINS's
    recomputed one (vicon2gt): within the threshold (measured 1.70 / 0.33 deg median)."""
    root = require(shared_data / "euroc_v101_micro")
    imu = read_imu_csv(str(root / "mav0" / "imu0" / "data.csv"))
    medians = {}
    for name in ("V1_01_easy_original.txt", "V1_01_easy.txt"):
        motion = motion_from_file(root / "groundtruth_openvins" / name)
        res = gyro_agreement(motion, imu, motion.t0_ns)
        assert res is not None
        medians[name] = res.median_deg
    assert medians["V1_01_easy_original.txt"] > 2 * MAX_MEDIAN_DISAGREEMENT_DEG
    assert medians["V1_01_easy.txt"] < 0.5 * MAX_MEDIAN_DISAGREEMENT_DEG

"""The loop-closed frames between two adjusted keyframes, integrated from the IMU."""

from __future__ import annotations

import numpy as np

from datasets.synth import make_synthetic_sequence
from mapping.fuse import poses_at
from slam.core.messages import ImuBatch
from slam.runtime.end_of_run import imu_between_keyframes


def test_frames_between_keyframes_follow_the_imu() -> None:
    """The aggressive profile's first 4 s with its noisy, biased IMU: keyframes every fourth
    frame at their true poses, the frames between them 3 mm off (as tracking in fast motion
    leaves them). Integrated from the IMU and pinned to both keyframes, they come back to
    within half a millimetre; a new map segment and a gap longer than a second are left
    alone."""
    seq = make_synthetic_sequence("aggressive", 4.0, 3)
    assert seq.ground_truth is not None
    t_ns = seq.frame_times_ns()
    truth = poses_at(seq.ground_truth, t_ns, max_gap_ns=10**9)
    rng = np.random.default_rng(0)
    noisy = truth.copy()
    noisy[:, :3, 3] += rng.normal(0.0, 0.003, (len(t_ns), 3))
    rows = np.arange(0, len(t_ns), 4)
    noisy[rows] = truth[rows]
    imu = seq.imu()
    batch = ImuBatch(imu.t_ns, imu.gyro_rad_s, imu.accel_m_s2)
    segments = np.zeros(len(t_ns), dtype=int)
    segments[60:] = 1  # frame 60 starts a new map (keyframes 56 and 60 span two segments)
    out = imu_between_keyframes(
        t_ns, noisy, rows, segments, batch, seq.calibration.imu.gravity_m_s2
    )
    between = np.setdiff1d(np.arange(rows[0], rows[-1]), rows)
    bridged = between[(between < 56) | (between > 60)]
    before = np.linalg.norm(noisy[bridged, :3, 3] - truth[bridged, :3, 3], axis=1)
    after = np.linalg.norm(out[bridged, :3, 3] - truth[bridged, :3, 3], axis=1)
    assert np.sqrt(np.mean(before**2)) > 0.004
    assert np.sqrt(np.mean(after**2)) < 0.0005
    rot_err = [np.linalg.norm(np.eye(3) - out[i, :3, :3].T @ truth[i, :3, :3]) for i in bridged]
    assert max(rot_err) < 0.005  # rad, about
    np.testing.assert_array_equal(out[57:60], noisy[57:60])  # across the new segment: as given
    np.testing.assert_array_equal(out[rows], noisy[rows])  # keyframes: as given
    # keyframes 1.2 s apart (a gap): the frames between them are left as they were
    sparse = np.array([0, 24, 28])
    out2 = imu_between_keyframes(
        t_ns, noisy, sparse, np.zeros(len(t_ns), int), batch, seq.calibration.imu.gravity_m_s2
    )
    np.testing.assert_array_equal(out2[1:24], noisy[1:24])
    assert not np.array_equal(out2[25:28], noisy[25:28])

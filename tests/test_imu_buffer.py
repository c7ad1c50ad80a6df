import numpy as np

from slam.imu_buffer import ImuBuffer, integrate_gyro, propagate_pose
from slam.messages import ImuSample


def _fill(buf: ImuBuffer, n: int, gyro=(0.0, 0.0, 1.0), accel=(0.0, 0.0, 9.81)) -> None:
    for i in range(n):
        buf.append(ImuSample(i * 5_000_000, np.array(gyro), np.array(accel)))


def test_window_covers_the_interval_and_old_samples_are_trimmed():
    buf = ImuBuffer(keep_ns=1_000_000_000)
    _fill(buf, 1000)
    w = buf.window(4_000_000_000, 4_050_000_000)
    assert w[0].t_ns <= 4_000_000_000 and w[-1].t_ns >= 4_050_000_000
    assert len(buf.window(0, 100_000_000)) <= 2  # forgotten: older than keep_ns x 2
    buf.append(ImuSample(10, np.zeros(3), np.zeros(3)))  # out of order: ignored
    buf.append(ImuSample(5_000_000_000, np.full(3, np.nan), np.zeros(3)))  # NaN: ignored
    assert buf.window(4_990_000_000, 5_000_000_000)[-1].t_ns == 4_995_000_000


def test_gyro_integration_and_dead_reckoning_match_constant_motion():
    buf = ImuBuffer()
    _fill(buf, 400)  # 2 s, 1 rad/s about z, specific force balancing gravity: no acceleration
    rot = integrate_gyro(buf.window(0, 1_000_000_000), 0, 1_000_000_000)
    assert rot is not None
    assert abs(np.arctan2(rot[1, 0], rot[0, 0]) - 1.0) < 1e-9
    pose, vel = propagate_pose(
        buf.window(0, 1_000_000_000),
        0,
        1_000_000_000,
        np.eye(4),
        np.array([1.0, 0.0, 0.0]),
        np.zeros(3),
        np.zeros(3),
        9.81,
    )
    np.testing.assert_allclose(pose[:3, 3], [1.0, 0.0, 0.0], atol=1e-9)
    np.testing.assert_allclose(vel, [1.0, 0.0, 0.0], atol=1e-9)
    assert (
        integrate_gyro(buf.window(3_000_000_000, 4_000_000_000), 3_000_000_000, 4_000_000_000)
        is None
    )

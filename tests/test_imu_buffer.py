import numpy as np

from slam.core.messages import ImuSample
from slam.imu_buffer import ImuBuffer, integrate_gyro, propagate_pose


def _fill(buf: ImuBuffer, n: int, gyro=(0.0, 0.0, 1.0), accel=(0.0, 0.0, 9.81)) -> None:
    for i in range(n):
        buf.add(ImuSample(i * 5_000_000, np.array(gyro), np.array(accel)))


def test_window_covers_the_interval_and_old_samples_are_trimmed():
    buf = ImuBuffer(keep_ns=1_000_000_000)
    _fill(buf, 1000)
    w = buf.window(4_000_000_000, 4_050_000_000)
    assert w[0].t_ns <= 4_000_000_000 and w[-1].t_ns >= 4_050_000_000
    assert len(buf.window(0, 100_000_000)) <= 2  # forgotten: older than keep_ns x 2
    buf.add(ImuSample(10, np.zeros(3), np.zeros(3)))  # out of order: ignored
    buf.add(ImuSample(5_000_000_000, np.full(3, np.nan), np.zeros(3)))  # NaN: ignored
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


def test_dead_reckoning_matches_the_per_sample_recurrence_and_constant_acceleration():
    """The vectorised propagation equals the per-sample recurrence it replaced (the
    specification, written out here) on random motion, and the analytic result for a constant
    acceleration."""
    from slam.core.geometry import so3_exp, so3_exp_batch

    rng = np.random.default_rng(3)
    omegas = np.vstack([rng.normal(0, 1, (50, 3)), np.zeros((1, 3)), np.full((1, 3), 1e-8)])
    expected = np.array([so3_exp(w) for w in omegas])
    np.testing.assert_allclose(so3_exp_batch(omegas), expected, atol=1e-12)

    samples = [
        ImuSample(
            i * 5_000_000 + int(rng.integers(0, 1000)), rng.normal(0, 1, 3), rng.normal(0, 3, 3)
        )
        for i in range(60)
    ]
    t0, t1 = 7_000_000, 280_000_000
    start = np.eye(4)
    start[:3, :3] = so3_exp(np.array([0.1, -0.2, 0.3]))
    start[:3, 3] = [1.0, 2.0, 3.0]
    v0, bg, ba = np.array([0.3, -0.1, 0.2]), np.full(3, 0.01), np.full(3, -0.05)
    rot, pos, vel = start[:3, :3].copy(), start[:3, 3].copy(), v0.copy()
    g = np.array([0.0, 0.0, -9.81])
    for k, s in enumerate(samples):
        a, b = max(s.t_ns, t0), min(samples[k + 1].t_ns if k + 1 < len(samples) else t1, t1)
        if b <= a:
            continue
        dt = (b - a) * 1e-9
        acc = rot @ (s.accel_m_s2 - ba) + g
        pos, vel = pos + vel * dt + 0.5 * acc * dt * dt, vel + acc * dt
        rot = rot @ so3_exp((s.gyro_rad_s - bg) * dt)
    out = propagate_pose(samples, t0, t1, start, v0, bg, ba, 9.81)
    assert out is not None
    np.testing.assert_allclose(out[0][:3, :3], rot, atol=1e-12)
    np.testing.assert_allclose(out[0][:3, 3], pos, atol=1e-12)
    np.testing.assert_allclose(out[1], vel, atol=1e-12)
    gyro_only = integrate_gyro(samples, t0, t1, bg)
    np.testing.assert_allclose(gyro_only, start[:3, :3].T @ rot, atol=1e-12)

    buf = ImuBuffer()
    _fill(buf, 400, gyro=(0.0, 0.0, 0.0), accel=(0.5, 0.0, 9.81))  # 0.5 m/s^2 along x
    out = propagate_pose(buf.window(0, 10**9), 0, 10**9, np.eye(4), np.zeros(3), *np.zeros((2, 3)))
    assert out is not None
    np.testing.assert_allclose(out[0][:3, 3], [0.25, 0.0, 0.0], atol=1e-12)
    np.testing.assert_allclose(out[1], [0.5, 0.0, 0.0], atol=1e-12)


def _messy_batches(seed: int) -> list[list[ImuSample]]:
    """Batches of samples with every problem the buffer checks: NaNs, saturation, repeated and
    late stamps, gaps."""
    rng = np.random.default_rng(seed)
    t, batches = 1_000_000_000, []
    for _ in range(30):
        batch = []
        for _ in range(int(rng.integers(0, 15))):
            r = rng.random()
            step = 5_000_000 if r > 0.1 else int(rng.choice([0, -7_000_000, 80_000_000]))
            t += step
            gyro = rng.normal(0, 1, 3)
            accel = rng.normal(0, 5, 3) + [0, 0, 9.81]
            if rng.random() < 0.05:
                gyro[int(rng.integers(3))] = np.nan
            if rng.random() < 0.05:
                accel[int(rng.integers(3))] = 200.0
            batch.append(ImuSample(t, gyro, accel))
        batches.append(batch)
    return batches


def test_batch_checks_keep_and_count_what_sample_by_sample_checks_do():
    """``extend`` (numpy over a batch) keeps the same samples, in the same order, with the same
    counts and warnings as ``add`` one sample at a time, from an empty buffer and across
    batches."""
    for seed in range(5):

        def buffer() -> ImuBuffer:
            return ImuBuffer(
                keep_ns=None,
                max_gyro_rad_s=3.0,
                max_accel_m_s2=60.0,
                gap_warn_ns=50_000_000,
                log_problems=True,
            )

        one, many = buffer(), buffer()
        for batch in _messy_batches(seed):
            kept_one = sum(one.add(s) for s in batch)
            assert many.extend(batch) == kept_one
        t1, g1, a1 = one.arrays()
        t2, g2, a2 = many.arrays()
        np.testing.assert_array_equal(t1, t2)
        np.testing.assert_array_equal(g1, g2)
        np.testing.assert_array_equal(a1, a2)
        assert one.stats == many.stats
        s = one.stats
        assert min(s.rejected_nonfinite, s.rejected_saturated, s.rejected_out_of_order) > 0
        assert s.gaps_warned > 0 and len(s.messages) == 4  # the first of each kind

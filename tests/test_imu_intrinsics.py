"""Online IMU intrinsics (``slam.backend.imu_intrinsics``) against injected truth, and the IMU
store applying them."""

from __future__ import annotations

import numpy as np

from datasets.rigs import euroc_like_calibration
from datasets.synth.imu_sim import ImuEffects, simulate_imu
from datasets.synth.trajectories import make_profile
from slam.backend.config import BackendConfig
from slam.backend.imu import integration_pieces
from slam.backend.imu_intrinsics import KeyframeState, OnlineImuIntrinsics, fit_intrinsics
from slam.core.geometry import so3_exp_batch
from slam.core.messages import ImuIntrinsics, ImuSample
from slam.imu_buffer import ImuBuffer

GRAVITY = np.array([0.0, 0.0, -9.81])
IMU = euroc_like_calibration(None).imu


def _states(
    profile: str,
    duration_s: float,
    effects: ImuEffects,
    seed: int,
    rot_noise_rad: float = 5e-5,
    pos_noise_m: float = 1e-4,
) -> tuple[list[KeyframeState], object]:
    """Keyframe states every 0.1 s from the true motion (vision-like noise on rotation and
    position; velocity from the truth, which the fit does not use) and the raw IMU pieces."""
    calib = euroc_like_calibration(None)
    assert calib.imu is not None
    motion = make_profile(profile)
    t_ns = np.arange(0, int(duration_s * 1e9) + 1, 5_000_000, dtype=np.int64)
    sim = simulate_imu(motion, t_ns, 0.0, calib.imu, noise=True, seed=seed, effects=effects)
    kf_t = t_ns[::20]
    truth = motion.sample(kf_t * 1e-9)
    rng = np.random.default_rng(seed + 100)
    noise_rot = so3_exp_batch(rng.standard_normal((len(kf_t), 3)) * rot_noise_rad)
    states = []
    for i, t in enumerate(kf_t.tolist()):
        pieces = None
        if i:
            pieces = integration_pieces(
                sim.arrays.t_ns, sim.arrays.gyro_rad_s, sim.arrays.accel_m_s2, kf_t[i - 1], t, 0.1
            )
        states.append(
            KeyframeState(
                t_ns=t,
                world_from_body_rot=truth.world_from_body_rot[i] @ noise_rot[i],
                position_world_m=truth.positions_m[i] + rng.standard_normal(3) * pos_noise_m,
                velocity_world_m_s=truth.velocities_m_s[i],
                pieces_from_previous=pieces,
            )
        )
    return states, sim.distortion


def test_fit_recovers_injected_scale_and_misalignment() -> None:
    """20 s of the aggressive profile with 0.3 % scale errors and 3 mrad misalignment (3x the
    bundle's, so it stands above the noise), keyframe states 0.05 mrad / 0.1 mm noisy: the
    gyro's correction matrix equals the inverse of the injected one within 0.04 % per entry,
    the accelerometer's within 0.1 %, each at least 4x (gyro 10x) smaller than the injected
    errors, and within 3.5 of the fit's own standard deviations."""
    effects = ImuEffects(scale_error_std=0.003, misalignment_std_rad=0.003)
    states, distortion = _states("aggressive", 20.0, effects, seed=5)
    fit = fit_intrinsics(states, GRAVITY, ImuIntrinsics.identity(), prior_sigma=0.01)
    assert fit is not None
    for found, injected, std, tol, gain in (
        (fit.gyro_matrix, distortion.gyro_matrix, fit.gyro_std, 4e-4, 10),
        (fit.accel_matrix, distortion.accel_matrix, fit.accel_std, 1e-3, 4),
    ):
        truth = np.linalg.inv(injected)
        err = np.abs(found - truth)
        assert err.max() < tol, (found, truth)
        assert np.abs(truth - np.eye(3)).max() > gain * err.max()
        assert np.all(err < 3.5 * std)


def test_no_effects_fit_stays_at_identity() -> None:
    states, _ = _states("aggressive", 15.0, ImuEffects(), seed=6)
    fit = fit_intrinsics(states, GRAVITY, ImuIntrinsics.identity(), prior_sigma=0.01)
    assert fit is not None
    assert np.abs(fit.gyro_matrix - np.eye(3)).max() < 5e-4
    assert np.abs(fit.accel_matrix - np.eye(3)).max() < 1e-3


def test_scale_only_model_holds_the_off_diagonals() -> None:
    effects = ImuEffects(scale_error_std=0.003)
    states, distortion = _states("aggressive", 15.0, effects, seed=7)
    fit = fit_intrinsics(
        states, GRAVITY, ImuIntrinsics.identity(), prior_sigma=0.01, misalignment=False
    )
    assert fit is not None
    off = ~np.eye(3, dtype=bool)
    assert np.abs(fit.gyro_matrix[off]).max() < 1e-6
    for found, injected, tol in (
        (fit.gyro_matrix, distortion.gyro_matrix, 3e-4),
        (fit.accel_matrix, distortion.accel_matrix, 1e-3),
    ):
        truth = 1.0 / np.diag(injected)
        assert np.abs(np.diag(found) - truth).max() < tol


def test_gate_waits_for_excitation() -> None:
    """A gentle figure-8 for 6 s does not determine the scales to 0.05 %: nothing applied
    (the identity stays); the aggressive profile does, and the matrices are applied."""
    cfg = BackendConfig(
        imu_intrinsics_online=True,
        imu_intrinsics_min_span_s=5.0,
        imu_intrinsics_apply_std=0.0005,
        imu_intrinsics_min_correction=0.0,
        imu_intrinsics_accel=True,
    )
    effects = ImuEffects(scale_error_std=0.003, misalignment_std_rad=0.001)
    gentle, _ = _states("figure8", 6.0, effects, seed=8)
    est = OnlineImuIntrinsics(cfg, IMU)
    for s in gentle:
        est.add_state(s)
    assert est.update() is None
    assert est.applied.is_identity and est.status == "too little excitation"
    fast, distortion = _states("aggressive", 15.0, effects, seed=8)
    est = OnlineImuIntrinsics(cfg, IMU)
    for s in fast:
        est.add_state(s)
    applied = est.update()
    assert applied is not None and est.gyro_applied_t_ns == fast[-1].t_ns
    assert np.abs(applied.gyro_matrix - np.linalg.inv(distortion.gyro_matrix)).max() < 4e-4
    summary = est.summary()
    assert summary["status"].endswith("applied") and summary["fits"] == 1


def test_buffer_applies_intrinsics_to_every_reading() -> None:
    buf = ImuBuffer(keep_ns=None)
    rng = np.random.default_rng(1)
    samples = [
        ImuSample(i * 5_000_000, rng.standard_normal(3), rng.standard_normal(3) + [0, 0, 9.81])
        for i in range(20)
    ]
    buf.extend(samples)
    plain = buf.window(0, 10**9)
    np.testing.assert_array_equal(plain[3].gyro_rad_s, samples[3].gyro_rad_s)
    g = np.eye(3) + np.diag([0.003, -0.002, 0.001])
    a = np.eye(3) + 0.001 * np.array([[0, 1, 0], [0, 0, 2], [1, 0, 0]])
    buf.set_intrinsics(ImuIntrinsics(g, a))
    t, gyro, accel = buf.arrays()
    np.testing.assert_allclose(gyro[5], g @ samples[5].gyro_rad_s)
    np.testing.assert_allclose(accel[5], a @ samples[5].accel_m_s2)
    corrected = buf.window(0, 10**9)
    np.testing.assert_allclose(corrected[7].accel_m_s2, a @ samples[7].accel_m_s2)
    raw_t, raw_g, _ = buf.raw_arrays()
    np.testing.assert_array_equal(raw_g[5], samples[5].gyro_rad_s)
    buf.set_intrinsics(ImuIntrinsics.identity())
    assert buf.window(0, 10**9)[3] is plain[3]  # the stored samples themselves again
    np.testing.assert_array_equal(buf.arrays()[1][5], samples[5].gyro_rad_s)


def test_small_corrections_are_not_applied() -> None:
    """``imu_intrinsics_min_correction``: a calibrated IMU (no effects) fits within 0.05 % of
    the identity and is left as read; 0.3 % scale errors (the largest drawn here 0.7 %) are
    applied."""
    cfg = BackendConfig(
        imu_intrinsics_online=True, imu_intrinsics_min_correction=0.002, imu_intrinsics_accel=True
    )
    clean, _ = _states("aggressive", 12.0, ImuEffects(), seed=10)
    est = OnlineImuIntrinsics(cfg, IMU)
    for s in clean:
        est.add_state(s)
    assert est.update() is None and est.applied.is_identity
    assert est.status.startswith("calibrated")
    assert len(est.fits) == 1
    effects = ImuEffects(scale_error_std=0.003)
    off, distortion = _states("aggressive", 12.0, effects, seed=10)
    assert np.abs(np.diag(distortion.gyro_matrix) - 1).max() > 0.002
    est = OnlineImuIntrinsics(cfg, IMU)
    for s in off:
        est.add_state(s)
    applied = est.update()
    assert applied is not None and not applied.is_identity


def test_backend_fits_without_changing_the_run_until_it_applies() -> None:
    """The back end on the simulated world (20 s of gentle flight, 0.3 % scale errors, 1 mrad
    misalignment): with the 0.05 % gate nothing is applied (its fits are 0.1-0.2 % uncertain
    there), every estimate equals the run without the estimation, and the fits are reported."""
    from datasets.synth.vio_world import generate_world
    from slam.backend.smoother import VioBackend

    effects = ImuEffects(scale_error_std=0.003, misalignment_std_rad=0.001)
    world = generate_world(duration_s=20.0, seed=3, start_s=1.0, imu_effects=effects)
    poses = []
    backends = []
    for on in (False, True):
        cfg = BackendConfig(imu_intrinsics_online=on, imu_intrinsics_apply_std=0.0005)
        be = VioBackend(world.calibration, cfg)
        out = []
        for m in world.messages():
            if isinstance(m, ImuSample):
                be.add_imu(m)
            else:
                est = be.add_keyframe(m)
                assert est is not None and est.imu_intrinsics is None
                out.append(est.world_from_body)
        poses.append(np.array(out))
        backends.append(be)
    np.testing.assert_array_equal(poses[0], poses[1])
    est = backends[1].intrinsics
    assert est is not None and est.applied.is_identity
    summary = est.summary()
    assert summary["fits"] >= 4 and summary["status"] == "too little excitation"
    assert summary["gyro_applied_t_ns"] == -1

"""Camera and IMU effects of the synthetic generator, each against its model: blur length against
angular rate x exposure, the vignetting profile, the stereo gain ratio, auto-exposure's gain
steps, signal-dependent noise, rolling-shutter skew, the time offset, the extrinsics error,
vibration spectrum, scale and misalignment, determinism."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from scipy.signal import welch

from datasets.rigs import euroc_like_calibration
from datasets.sequence import ImuArrays
from datasets.synth import make_synthetic_sequence
from datasets.synth.camera_model import (
    CameraEffects,
    exposure_schedule,
    realistic_camera,
    vignetting_profile,
)
from datasets.synth.generator import SyntheticSequence, SynthOptions
from datasets.synth.imu_sim import ImuEffects, exact_imu, simulate_imu
from datasets.synth.scene import build_scene
from datasets.synth.trajectories import ProfileMotion, SinusoidChannel, TimeWarp
from slam.core.calibration import ImuCalibration
from slam.core.errors import InputError
from slam.core.geometry import rotation_angle_rad
from slam.core.messages import mid_exposure_ns
from slam.core.trajectory import Trajectory


def _spinning_sequence(yaw_rate_rad_s: float, camera: CameraEffects) -> SyntheticSequence:
    """A camera at (1, 0, 1.5) m turning about world z at a constant rate, facing +x at t = 1 s,
    in the room without boxes."""
    scene = build_scene("room", max_boxes=0)
    motion = ProfileMotion(
        name="spin",
        x=SinusoidChannel(c0=1.0),
        y=SinusoidChannel(c0=0.0),
        z=SinusoidChannel(c0=1.5),
        yaw=SinusoidChannel(c0=-yaw_rate_rad_s * 1.0, c1=yaw_rate_rad_s),
        pitch=SinusoidChannel(),
        roll=SinusoidChannel(),
        warp=TimeWarp(0.0, 0.0),
    )
    frame_times = np.arange(0, 2_000_000_001, 50_000_000, dtype=np.int64)
    imu_times = np.arange(0, 2_000_000_001, 5_000_000, dtype=np.int64)
    calib = euroc_like_calibration()
    gt = Trajectory.from_matrices(imu_times, motion.sample(imu_times * 1e-9).world_from_body())
    empty = ImuArrays(np.zeros(0, np.int64), np.zeros((0, 3)), np.zeros((0, 3)))
    return SyntheticSequence(
        name="spin",
        calibration=calib,
        motion=motion,
        motion_t0_s=0.0,
        scene=scene,
        frame_times_ns=frame_times,
        imu=empty,
        ground_truth=gt,
        options=SynthOptions(profile="spin", camera=camera),
    )


def _box_kernel(length_px: float, shift_px: float = 0.0) -> np.ndarray:
    """Horizontal box of a fractional length (unit sum) centred at ``shift_px``."""
    half = length_px / 2.0
    n = int(np.ceil(half + abs(shift_px) + 0.5))
    x = np.arange(-n, n + 1, dtype=float)
    lo, hi = shift_px - half, shift_px + half
    w = np.clip(np.minimum(x + 0.5, hi) - np.maximum(x - 0.5, lo), 0.0, None)
    return (w / w.sum())[None, :].astype(np.float32)


def _mid_exposure_view(
    seq: SyntheticSequence, index: int, exposure_s: float
) -> tuple[np.ndarray, np.ndarray]:
    """Frame ``index``'s left image (float32) and cam0's sharp radiance rendered at the middle
    of its exposure window ``[stamp - exposure_s, stamp]``."""
    mid_ns = int(seq.frame_times_ns()[index] - exposure_s / 2 * 1e9)
    cam = seq.calibration.cam0
    sharp = seq.renderer.cameras[0].render_radiance(
        seq.world_from_body_at(mid_ns) @ cam.body_from_cam
    )
    return sharp, seq.frame(index).left.astype(np.float32)


def test_motion_blur_length_is_angular_rate_times_exposure() -> None:
    """The blurred image is the sharp one (rendered at mid-exposure) convolved with a horizontal
    box of length f * omega * exposure (the image moves f * omega px/s near the centre): the
    best-fitting box length must be that."""
    omega, exposure_s = 2.0, 0.008
    blurred = _spinning_sequence(omega, CameraEffects(exposure_s=exposure_s))
    index = 20
    sharp, image = _mid_exposure_view(blurred, index, exposure_s)
    cam = blurred.calibration.cam0
    centre = np.s_[160:320, 226:526]
    lengths = np.arange(0.1, 14.0, 0.1)
    errors = [
        float(np.abs(cv2.filter2D(sharp, -1, _box_kernel(L))[centre] - image[centre]).mean())
        for L in lengths
    ]
    best = lengths[int(np.argmin(errors))]
    expected_px = cam.intrinsics.fx * omega * exposure_s
    assert blurred.subframes(index) >= 4
    assert abs(best - expected_px) < 0.06 * expected_px, (best, expected_px)
    unblurred = float(np.abs(sharp[centre] - image[centre]).mean())
    assert min(errors) < 0.15 * unblurred  # a box blur explains the image; no blur does not


def test_blurred_image_is_centred_on_its_mid_exposure_view() -> None:
    """The streak's centroid is the mid-exposure projection: of boxes of the expected length
    shifted along the streak, the centred one explains the blurred image (with sensor noise)
    best, to 0.05 px; a box ending at the image's stamp (the exposure's end) is 5.7 px off.
    A shift here is what a tracked feature would inherit as an along-streak bias."""
    omega, exposure_s = 2.0, 0.008
    seq = _spinning_sequence(
        omega, CameraEffects(exposure_s=exposure_s, read_noise_std=1.2, shot_noise_gl=1 / 40)
    )
    sharp, image = _mid_exposure_view(seq, 20, exposure_s)
    cam = seq.calibration.cam0
    centre = np.s_[160:320, 226:526]
    length_px = cam.intrinsics.fx * omega * exposure_s
    shifts = np.arange(-1.0, 1.0001, 0.02)

    def error(shift: float) -> float:
        blurred = cv2.filter2D(sharp, -1, _box_kernel(length_px, shift))
        return float(np.square(blurred[centre] - image[centre]).mean())

    errors = [error(d) for d in shifts]
    best = shifts[int(np.argmin(errors))]
    assert abs(best) < 0.05, best
    assert error(length_px / 2) > 3 * min(errors)


def test_rolling_shutter_skews_rows_by_line_delay() -> None:
    """Each row is seen (row - centre) * line_delay later: under a yaw rate the bottom of the
    image is shifted against the top by f * omega * delay * rows."""
    omega, delay_s = 2.0, 50e-6
    seq = _spinning_sequence(omega, CameraEffects(line_delay_s=delay_s))
    gs = seq.renderer.cameras[0].render(seq.world_from_cam(20)).image.astype(np.float32)
    rs = seq.frame(20).left.astype(np.float32)
    win = (np.hanning(64)[:, None] * np.hanning(700)[None, :]).astype(np.float32)
    shifts = []
    for r0 in (16, 400):
        (dx, _), _ = cv2.phaseCorrelate(gs[r0 : r0 + 64, 26:726], rs[r0 : r0 + 64, 26:726], win)
        shifts.append(dx)
    expected = seq.calibration.cam0.intrinsics.fx * omega * delay_s * 384
    assert abs(abs(shifts[1] - shifts[0]) - expected) < 0.1 * expected, (shifts, expected)


@pytest.fixture(scope="module")
def clean_frame():
    seq = make_synthetic_sequence("figure8", duration_s=0.5, seed=3)
    return seq.frame(2)


def test_vignetting_follows_cos4_profile(clean_frame) -> None:
    seq = make_synthetic_sequence("figure8", 0.5, 3, camera=CameraEffects(vignetting=0.3))
    img = seq.frame(2).left.astype(float)
    clean = clean_frame.left.astype(float)
    intr = seq.calibration.cam0.intrinsics
    vv, uu = np.mgrid[0 : intr.height, 0 : intr.width]
    r = np.hypot(uu - intr.cx, vv - intr.cy)
    r_max = max(np.hypot(x - intr.cx, y - intr.cy) for x in (0, 751) for y in (0, 479))
    rho = r / r_max
    ok = clean > 60
    measured = img[ok] / clean[ok]
    model = vignetting_profile(0.3, rho[ok])
    for lo in np.arange(0.0, 0.95, 0.1):
        sel = (rho[ok] >= lo) & (rho[ok] < lo + 0.1)
        assert abs(np.median(measured[sel] / model[sel]) - 1.0) < 0.01, lo
    assert model.min() < 0.75  # the corners are in the test
    assert vignetting_profile(0.3, 1.0) == pytest.approx(0.7)


def test_stereo_gain_mismatch_is_the_right_over_left_ratio(clean_frame) -> None:
    seq = make_synthetic_sequence("figure8", 0.5, 3, camera=CameraEffects(stereo_gain=1.08))
    f = seq.frame(2)
    assert np.abs(f.left.astype(int) - clean_frame.left.astype(int)).max() <= 1
    ok = (clean_frame.right > 40) & (clean_frame.right < 220)
    ratio = f.right[ok].astype(float) / clean_frame.right[ok]
    assert np.median(ratio) == pytest.approx(1.08, abs=0.005)


def test_sensor_noise_variance_grows_with_signal() -> None:
    """Residual variance against the float radiance: read^2 + shot * signal (+ 1/12 rounding)."""
    fx = CameraEffects(read_noise_std=2.0, shot_noise_gl=0.1)
    seq = make_synthetic_sequence("figure8", 0.5, 5, camera=fx)
    radiance = seq.renderer.cameras[0].render_radiance(seq.world_from_cam(2))
    resid = seq.frame(2).left.astype(float) - radiance
    signal, var = [], []
    for lo in range(20, 220, 20):
        sel = (radiance >= lo) & (radiance < lo + 20)
        if sel.sum() > 2000:
            signal.append(radiance[sel].mean())
            var.append(resid[sel].var() - 1 / 12)
    slope, intercept = np.polyfit(signal, var, 1)
    assert slope == pytest.approx(0.1, rel=0.1)
    assert intercept == pytest.approx(4.0, rel=0.25)


def test_auto_exposure_tracks_illumination_with_abrupt_gain_steps() -> None:
    """During the still start the images differ only by brightness: measured against the clean
    frame it must be the schedule's B = L G E / E_ref; AE keeps it near 1 while the light varies
    by more than x8, and each gain step moves one frame's brightness by the step."""
    fx = CameraEffects(
        auto_exposure=True, illumination_log_amplitude=1.5, illumination_period_s=4.0
    )
    seq = make_synthetic_sequence("figure8", 1.9, 2, camera=fx)
    clean = make_synthetic_sequence("figure8", 0.1, 2).frame(0).left.astype(float)
    ex = seq.exposure
    ok = (clean > 30) & (clean < 120)
    measured = np.array(
        [np.median(seq.frame(k).left[ok] / clean[ok]) for k in range(seq.num_frames)]
    )
    np.testing.assert_allclose(measured, ex.brightness, rtol=0.02)
    steps = np.flatnonzero(np.diff(ex.gain) != 0) + 1
    assert len(steps) >= 2
    light = ex.illumination
    assert light.max() / light.min() > 8
    for k in steps:
        jump = measured[k] / measured[k - 1] / (light[k] / light[k - 1])
        step = ex.gain[k] / ex.gain[k - 1]
        assert jump == pytest.approx(step, rel=0.03)
    calm = np.setdiff1d(np.arange(seq.num_frames), steps)
    assert np.abs(np.log(measured[calm])).max() < 0.35
    # exposures stay within the AE's bounds; more light, shorter exposure
    assert ex.exposure_s.min() >= fx.exposure_min_s and ex.exposure_s.max() <= fx.exposure_max_s
    assert np.corrcoef(np.log(light), np.log(ex.exposure_s * ex.gain))[0, 1] < -0.9


def test_time_offset_and_extrinsic_error_change_what_the_images_show() -> None:
    clean = make_synthetic_sequence("aggressive", 4.0, 1)
    late = make_synthetic_sequence(
        "aggressive", 4.0, 1, time_offset_ns=20_000_000, calib_rotation_error_deg=(0.0, 2.0, 0.0)
    )
    np.testing.assert_array_equal(late.frame_times_ns(), clean.frame_times_ns())
    np.testing.assert_array_equal(late.imu().gyro_rad_s, clean.imu().gyro_rad_s)
    assert late.calibration.time_offset_ns == 0
    i = 70
    shown = late.renderer.render(
        late.world_from_body_at(int(late.frame_times_ns()[i]) + 20_000_000)
    )
    np.testing.assert_array_equal(late.frame(i).left, shown[0].image)
    assert not np.array_equal(late.frame(i).left, clean.frame(i).left)
    given = late.calibration.cam0.body_from_cam[:3, :3]
    true = late.true_calibration.cam0.body_from_cam[:3, :3]
    assert np.degrees(rotation_angle_rad(given @ true.T)) == pytest.approx(2.0)
    np.testing.assert_allclose(
        late.calibration.stereo_baseline_m(), clean.calibration.stereo_baseline_m()
    )


def test_imu_vibration_spectrum_peaks_at_its_frequency() -> None:
    motion = make_synthetic_sequence("figure8", 0.1).motion
    t_ns = np.arange(0, 30_000_000_001, 5_000_000, dtype=np.int64)
    calib = ImuCalibration(rate_hz=200.0)
    fx = ImuEffects(vibration_accel_rms_m_s2=0.8, vibration_gyro_rms_rad_s=0.02, vibration_hz=61.0)
    sim = simulate_imu(motion, t_ns, 0.0, calib, noise=False, effects=fx, seed=4)
    gyro, accel = exact_imu(motion, t_ns * 1e-9, calib.gravity_m_s2)
    vib_acc = sim.arrays.accel_m_s2 - accel
    vib_gyro = sim.arrays.gyro_rad_s - gyro
    assert np.sqrt((vib_acc**2).sum(1).mean()) == pytest.approx(0.8, rel=0.05)
    assert np.sqrt((vib_gyro**2).sum(1).mean()) == pytest.approx(0.02, rel=0.05)
    f, p = welch(np.linalg.norm(vib_acc, axis=1) * np.sign(vib_acc[:, 0]), fs=200.0, nperseg=1024)
    assert abs(f[np.argmax(p)] - 61.0) < 1.5
    band = np.abs(f - 61.0) < 6.0
    assert p[band].sum() > 0.95 * p.sum()  # narrow band


def test_imu_scale_and_misalignment_are_a_fixed_linear_map() -> None:
    motion = make_synthetic_sequence("aggressive", 0.1).motion
    t_ns = np.arange(0, 20_000_000_001, 5_000_000, dtype=np.int64)
    calib = ImuCalibration(rate_hz=200.0)
    fx = ImuEffects(scale_error_std=0.01, misalignment_std_rad=0.005)
    sim = simulate_imu(motion, t_ns, 0.0, calib, noise=True, effects=fx, seed=9)
    gyro, _ = exact_imu(motion, t_ns * 1e-9, calib.gravity_m_s2)
    fit, *_ = np.linalg.lstsq(gyro, sim.arrays.gyro_rad_s - sim.gyro_bias_rad_s, rcond=None)
    assert sim.distortion is not None
    np.testing.assert_allclose(fit.T, sim.distortion.gyro_matrix, atol=1e-3)
    off = sim.distortion.gyro_matrix - np.diag(np.diag(sim.distortion.gyro_matrix))
    assert 0.001 < np.abs(off).max() < 0.03
    assert 0.002 < np.abs(np.diag(sim.distortion.gyro_matrix) - 1).max() < 0.05
    plain = simulate_imu(motion, t_ns, 0.0, calib, noise=True, seed=9)
    # the noise stream is the same with and without effects
    np.testing.assert_array_equal(plain.gyro_bias_rad_s, sim.gyro_bias_rad_s)


def test_realistic_bundle_is_deterministic_by_seed() -> None:
    a = make_synthetic_sequence("figure8", 3.0, 7, camera=realistic_camera())
    b = make_synthetic_sequence("figure8", 3.0, 7, camera=realistic_camera())
    c = make_synthetic_sequence("figure8", 3.0, 8, camera=realistic_camera())
    fa, fb, fc = a.frame(50), b.frame(50), c.frame(50)
    np.testing.assert_array_equal(fa.left, fb.left)
    np.testing.assert_array_equal(fa.right, fb.right)
    assert not np.array_equal(fa.left, fc.left)
    np.testing.assert_array_equal(a.exposure.exposure_s, b.exposure.exposure_s)
    assert not np.array_equal(a.exposure.illumination, c.exposure.illumination)


def test_ground_truth_holds_each_images_mid_exposure_pose() -> None:
    """With exposures, the ground truth has the exact pose at every frame's mid-exposure stamp
    (what the player stamps the frame with) besides the 200 Hz grid, so nearest association
    pairs each estimate with its own time; without exposures it is the grid alone."""
    seq = make_synthetic_sequence("aggressive", 2.0, 3, camera=realistic_camera())
    gt = seq.ground_truth
    assert gt is not None
    exposures = seq.exposures_ns()
    assert exposures is not None
    mids = mid_exposure_ns(seq.frame_times_ns(), exposures)
    assert np.all(np.diff(gt.t_ns) > 0)
    assert np.isin(seq.imu().t_ns, gt.t_ns).all()
    assert np.isin(mids[mids >= gt.t_ns[0]], gt.t_ns).all()
    assert (mids % 5_000_000 != 0).sum() > len(mids) // 2  # most are off the grid
    k = int(np.flatnonzero(gt.t_ns == mids[10])[0])
    truth = seq.world_from_body_at(int(mids[10]))
    np.testing.assert_allclose(gt.positions_m[k], truth[:3, 3], atol=1e-12)
    clean = make_synthetic_sequence("aggressive", 2.0, 3)
    assert clean.ground_truth is not None
    np.testing.assert_array_equal(clean.ground_truth.t_ns, clean.imu().t_ns)


def test_schedule_without_auto_exposure_keeps_brightness() -> None:
    ex = exposure_schedule(CameraEffects(exposure_s=0.006), np.arange(0, 5, 0.05))
    np.testing.assert_allclose(ex.brightness, 1.0)
    np.testing.assert_allclose(ex.exposure_s, 0.006)


def test_bad_effect_values_are_input_errors() -> None:
    with pytest.raises(InputError, match="vignetting"):
        make_synthetic_sequence("figure8", 1.0, camera=CameraEffects(vignetting=1.5))
    with pytest.raises(InputError, match="vibration_hz"):
        make_synthetic_sequence("figure8", 1.0, imu_effects=ImuEffects(vibration_hz=0.0))
    with pytest.raises(InputError, match="time offset"):
        make_synthetic_sequence("figure8", 1.0, time_offset_ns=2_000_000_000)

"""Configuration of the visual-inertial back end (one dataclass, nested into ``SlamConfig``)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

from slam.core.bounds import bounded


@dataclass(frozen=True)
class BackendConfig:
    """Every tunable of the back end. Units are in the names (else ``unit=``); defaults suit
    EuRoC-grade IMUs."""

    # --- IMU sanitising -------------------------------------------------------------------------
    max_accel_m_s2: float = bounded(16.0 * 9.81, gt=0)
    """Accelerometer saturation limit: samples with any |axis| above it are rejected."""
    max_gyro_rad_s: float = bounded(35.0, gt=0)
    """Gyroscope saturation limit: samples with any |axis| above it are rejected."""
    # bounds: a nominal interval is 1 sample period: at <= 1 every interval warns
    imu_gap_warn_factor: float = bounded(3.0, gt=1)
    """An interval longer than this many nominal sample periods is counted and warned about."""
    imu_gap_max_s: float = bounded(0.1, gt=0)
    """Longest interval integrated across; between keyframes spanning a longer gap there is no
    IMU factor (the estimator runs on vision, with a weak VO relative-pose factor)."""
    imu_buffer_s: float = bounded(30.0, gt=0)
    """IMU history kept (seconds before the newest keyframe) for integration and resets."""
    keyframe_waits_for_imu: bool = False
    """The back end's stage hands a keyframe to the estimator only once an IMU reading at or
    after its stamp has arrived (at the latest with the next keyframe, or at the end of the
    input), as VINS-Mono's estimator waits. Without it a keyframe whose next reading is still
    on its way (the player hands the readings on with each frame, up to the frame's stamp) has
    its interval's last piece integrated at the last reading held, not interpolated towards the
    next: in sequential and real-time runs on the fair V1_01 renders (readings 3 us after the
    frames) every interval lost half of one reading, and the global adjustment's monocular
    scale came out 0.2-0.3 % small (``--speed max`` runs, whose back end lags, were spared:
    BENCHMARKS.md, speedmax21). Off: a keyframe goes on at once."""

    imu_gyro_scale_error: float = bounded(0.005, ge=0, le=0.2)
    """Gyro scale / axis error (fraction) the IMU noise model allows for: each keyframe
    interval's gyro noise density grows by this times the mean rotation rate times the root
    of the interval (``slam/backend/imu.py`` ``scale_error_params``). 0: the calibration's
    densities as they are."""
    imu_accel_scale_error: float = bounded(0.005, ge=0, le=0.2)
    """The same for the accelerometer (times the mean specific force, gravity included)."""
    imu_accel_scale_error_of_deviation: bool = False
    """The accelerometer's term times the mean deviation of the specific force from its mean
    over the interval instead (the constant part is left to the bias state)."""
    imu_accel_density_factor: float = bounded(1.0, ge=1, le=100)
    """The calibration's accelerometer noise density times this in the IMU factors that allow
    for scale errors (either ``imu_*_scale_error`` > 0). At the bare calibrated density (an
    interval of constant specific force under ``imu_accel_scale_error_of_deviation``) the
    monocular window's elimination met "Indeterminate linear system" (hall: 4 back-end
    resets); x2 and x3 both end them, the monocular preset's 3 scored best (BENCHMARKS.md)."""

    # --- online IMU intrinsics (slam.backend.imu_intrinsics) ------------------------------------
    imu_intrinsics_online: bool = False
    """Estimate the gyro's and accelerometer's correction matrices (per-axis scale, axis
    misalignment) from the smoother's final keyframe states and apply them to every IMU
    reading (the back end's and the front end's ``ImuBuffer``). Off: realistic live / loop-closed
    ATE room-aggressive 6.29 / 1.39 -> 5.55 / 1.41 mm, room-figure8 4.08 / 1.93 -> 3.67 / 1.43,
    but room-loop 5.90 / 0.51 -> 7.33 / 0.67 (its gyro fit 0.3 % off); clean room-aggressive
    byte-identical (nothing applied). The other keys' defaults are those runs' (BENCHMARKS.md,
    imu17)."""
    imu_intrinsics_window_s: float = bounded(20.0, gt=0)
    """Keyframe states of the last this many seconds are fitted."""
    imu_intrinsics_min_span_s: float = bounded(5.0, ge=0)
    """No fit before the states span this long."""
    imu_intrinsics_every_s: float = bounded(2.0, gt=0)
    """Fit again after this much keyframe time."""
    imu_intrinsics_interval_s: float = bounded(0.5, gt=0)
    """Consecutive keyframe states are joined into intervals of at least this long for the
    fit (the accelerometer's error grows with the square of an interval, the states' noise
    does not)."""
    imu_intrinsics_prior_sigma: float = bounded(0.01, gt=0)
    """Each matrix entry is held to the identity's with this standard deviation (a direction
    the motion does not excite stays at the identity; the bias takes it)."""
    imu_intrinsics_apply_std: float = bounded(0.002, gt=0)
    """A sensor's fitted matrix is applied once each of its three scale factors is known to
    this standard deviation (the excitation gate); until then it keeps the last applied.
    0.0005 applied realistic room-aggressive's gyro only after 27 s (live 6.33 mm)."""
    imu_intrinsics_min_correction: float = bounded(0.003, ge=0, le=0.2)
    """A sensor's matrix is applied at all only once one of its scale factors is this far
    from 1 (a fraction), so a calibrated IMU is left as read: on clean room-aggressive the
    smoother's relative rotations are ~0.05 % off the truth and the first gyro fit (after
    8 s) 0.2 % off the identity; with 0.002 it was applied (live 4.31 -> 3.58 mm, loop-closed
    0.745 -> 0.764: a changed run, not a better estimate), with 0.003 nothing is (byte-identical)."""
    imu_intrinsics_accel: bool = False
    """Apply the accelerometer's fitted matrix too (False: the gyro's only; its fit is still
    reported). On realistic room-aggressive the accelerometer's fit was 0.1-0.5 % off the
    truth (the gyro's 0.05-0.1 %), and applying it did not pay (BENCHMARKS.md, imu17)."""
    imu_intrinsics_misalignment: bool = True
    """Fit the whole matrix (scale and misalignment); False: the diagonal (scales) only."""
    imu_intrinsics_scale_error: float = bounded(0.001, ge=0, le=0.2)
    """``imu_gyro_scale_error`` / ``imu_accel_scale_error`` in place of those once the
    sensor's matrix is applied (what is left of its scale error). Realistic room-aggressive,
    both sensors applied: 0.005 / 0.002 / 0.001 / 0: live 6.20 / 6.01 / 5.63 / 6.28 mm."""

    # --- initialisation -------------------------------------------------------------------------
    init_mode: str = "auto"
    """"auto" (still start if the IMU before the first keyframe is still, else moving start),
    "still" or "moving"."""
    still_window_s: float = bounded(1.0, gt=0)
    """Length of IMU history that must be still for a still start."""
    still_smoothing_s: float = bounded(0.1, ge=0)
    """Still test: readings are first averaged over this long (removes rotor vibration; on
    EuRoC V1_01 the raw accel-norm std is 0.2-0.3 m/s^2 while the vehicle stands still)."""
    still_accel_std_m_s2: float = bounded(0.15, gt=0)
    """Still test: std of every smoothed accelerometer axis over the window below this."""
    still_gyro_std_rad_s: float = bounded(0.015, gt=0)
    """Still test: std of every smoothed gyro axis over the window below this."""
    still_init_method: str = "kalman"
    """"kalman" (filterpy linear KF, the design card's tool) or "align" (scipy align_vectors on
    the mean accel); measured equal accuracy on EuRoC V1_01, "align" is ~50x cheaper."""
    # bounds: init.moving_init needs K >= 3 keyframes
    moving_init_keyframes: int = bounded(10, ge=3)
    """Minimum keyframes (VO poses + IMU between them) for the moving-start alignment; up to
    three times as many (the newest) are used."""
    moving_init_min_span_s: float = bounded(1.5, ge=0)
    """Minimum time span of the keyframes used for the moving-start alignment."""
    moving_init_max_gravity_error: float = bounded(0.5, gt=0, unit="m/s^2")
    """Reject the unconstrained gravity solution if | |g| - g0 | exceeds this and retry with
    more keyframes."""

    # bounds: the alignment's consistency check needs 4 keyframes
    mono_init_keyframes: int = bounded(10, ge=4)
    """Monocular start: keyframes (up-to-scale VO poses + the IMU between them) before the
    visual-inertial alignment (``slam.backend.mono_init``) is tried; up to three times as many (the
    newest) are used, so a failed attempt is retried on a longer window, then one that slides."""
    mono_init_min_span_s: float = bounded(1.0, ge=0)
    """Monocular start: minimum time span of those keyframes."""
    mono_init_max_gravity_error: float = bounded(0.5, gt=0, unit="m/s^2")
    """Monocular start: reject the alignment when |g| of its free solution is this far off."""
    mono_init_max_scale_std: float = bounded(0.02, gt=0)
    """Monocular start: reject the alignment when the scale's standard deviation (from the
    fit's residuals) is above this fraction of it: too little acceleration yet."""
    mono_init_max_scale_disagreement: float = bounded(0.1, gt=0)
    """Monocular start: reject the alignment when the first two thirds of its keyframes give
    a scale differing by more than this fraction (too little excitation to fix it)."""
    mono_init_accel_bias_sigma: float = bounded(0.1, gt=0, unit="m/s^2")
    """Monocular start: the prior holding the alignment's accelerometer bias near 0 (its row
    weighed against the velocity-per-second rows). On gentle motion a small bias is much of
    the acceleration that fixes the scale: held at 0, a 0.02 m/s^2 bias moved V1_01's first
    scales 2-3 %. 10 (nearly free) starts V1_01 3 s after the motion instead of 19 s, but the
    suite's four sequences came out worse with it (BENCHMARKS.md, mono18b): not the preset's."""
    mono_init_retry_accel_bias_sigma: float = bounded(0.0, ge=0, unit="m/s^2")
    """Monocular start: 0 = off. Else every alignment is also solved with this accelerometer-bias
    prior (nearly free: 10): the held one (``mono_init_accel_bias_sigma``) is kept where it
    passes and the free scale agrees with it (within two of the free fit's standard deviations),
    else the free one starts the smoother if it passes the same checks (its bias, scale,
    gravity, velocities). V1_01's real IMU: the held fits' std 3-6 % for 19 s, the free ones
    2.0 % 2.7 s after the motion began (``slam.backend.mono_init.align_mono``)."""
    mono_init_span_s: float = bounded(0.0, ge=0)
    """Monocular start: 0 = off. Else the alignment is also tried with fewer than
    ``mono_init_keyframes`` (at least ``mono_init_span_keyframes``) once they span this long:
    on slow motion keyframes come every 0.25-0.5 s, and time, not their number, is what the
    accelerations that fix the scale need. ``euroc-mono-imu`` sets 1.85 with
    ``mono_init_batch`` (``mono_init_batch_span_only``): alone, on the fair V1_01 renders the
    smoother, held by the loose ``prior_*`` sigmas on a slow take-off, ran 1.6-10 % large over
    its first 10 s (live Sim(3) 0.984 / 0.902 / 0.965; with the batch 0.984 / 0.968 / 0.972)
    and the live ATE median was 38.1 mm (with the batch 22.3, neither 47.5; BENCHMARKS.md,
    v101start19)."""
    mono_init_span_keyframes: int = bounded(6, ge=4, le_field="mono_init_keyframes")
    """Monocular start: the fewest keyframes ``mono_init_span_s`` and
    ``mono_init_early_max_scale_std`` try the alignment with."""
    # bounds: a fraction of the scale, like mono_init_max_scale_std (the stricter one applies)
    mono_init_early_max_scale_std: float = bounded(0.0, ge=0, lt=1)
    """Monocular start: 0 = off. Else the alignment is tried at every keyframe from
    ``mono_init_span_keyframes`` on (once they span ``mono_init_min_span_s``), and a window of
    fewer than ``mono_init_keyframes`` is accepted when the scale's standard deviation is at
    most this fraction of it (and ``mono_init_max_scale_std``; the other checks as always):
    the window's excitation, which that standard deviation measures, decides when the start
    comes, not the keyframes' number or a fixed span (``slam.backend.mono_init.start_gate``)."""

    mono_init_batch: bool = False
    """Monocular start: after an accepted alignment, one visual-inertial bundle adjustment over
    its whole window (every keyframe's metric pose, velocity and bias; the landmarks'
    projections and the IMU factors; ``slam.backend.mono_init.batch_start``, VINS-Mono's first
    window optimisation), and the smoother starts at the newest keyframe from its solution
    with its joint marginal (pose, velocity, bias) as the prior, instead of the alignment's
    newest state under the loose ``prior_*`` sigmas. The front end's map takes the batch's
    scale. On in ``euroc-mono-imu`` with ``mono_init_span_s`` and
    ``mono_init_batch_span_only`` (BENCHMARKS.md, v101start19: the fair V1_01 renders start
    3.19 -> 2.39 s after the motion, median of three, within 3 s); first measured on the
    real-IMU V1_01 render, whose IMU disagrees with its images, where it was worse with the
    span start (BENCHMARKS.md, mono18e)."""

    mono_init_batch_span_only: bool = False
    """Monocular start, with ``mono_init_batch``: only a start accepted on fewer than
    ``mono_init_keyframes`` keyframes (``mono_init_span_s``'s slow-motion window) is batch
    adjusted; one on the full window starts from the alignment as without the batch. The
    batch on every start (mono18e, one run each): room-figure8 loop-closed 15.07 -> 1.64 mm,
    but room-loop +9 / +10 % (live / loop-closed) and the hall's loop-closed +49 %. With this,
    full-window starts (room-figure8, room-aggressive) are byte-identical to the preset
    without the batch; on the span start it costs room-loop's loop-closed ATE 0.68 -> 0.82 mm
    (median of 3; live 6.81 -> 5.70; BENCHMARKS.md, v101start19)."""

    mono_scale_check_window_s: float = bounded(0.0, ge=0)
    """Monocular, after the start: every ``mono_scale_check_every_s`` the smoother's keyframe
    estimates of the last this many seconds are aligned with the IMU again (the start's
    alignment on metric poses: scale 1 expected); 0: no check."""
    mono_scale_check_every_s: float = bounded(1.0, gt=0)
    """How often the scale check runs (keyframe times)."""
    mono_scale_check_method: Literal["alignment", "imu_fit"] = "alignment"
    """"alignment": the start's alignment on the smoother's poses (its scale multiplies their
    position differences, so their noise shrinks it: 0.06-0.58 on a smoother whose truth is
    1.0); "imu_fit": the poses' positions fitted as a similarity of the IMU's trajectory over
    the window, bias free (``mono_init.check_scale_by_imu_fit``: 0.94-1.15 on good runs, but
    no consistent scale in a slipping smoother's poses; BENCHMARKS.md, scalecheck20)."""
    mono_scale_check_with_bias: bool = False
    """The scale check aligns the IMU less the smoother's newest accelerometer bias (else the
    raw IMU, its bias held near 0 by the start's prior)."""
    mono_scale_check_repeats: int = bounded(1, ge=1)
    """A correction needs this many counted checks in a row off by more than the tolerance on
    the same side (the newest one's scale and velocity are used); 1: every such check."""
    mono_scale_check_max_std: float = bounded(0.03, gt=0)
    """A check counts only when its scale's standard deviation is under this fraction."""
    mono_scale_check_tolerance: float = bounded(0.1, gt=0, lt=1)
    """A counted check whose scale is off 1 by more than this fraction restarts the smoother
    at the newest state with the check's velocity (the scale follows the velocity)."""

    mono_reinit_residual_m: float = bounded(0.0, ge=0)
    """Monocular, with the scale check on (``mono_scale_check_window_s`` > 0): 0 = off. Else
    the smoother's keyframe positions of the last ``mono_reinit_window_s`` are fitted to the
    IMU's trajectory (``mono_init.check_scale_by_imu_fit``) as often as the check runs, and a
    fit whose rms residual is above this re-initialises: the smoother is dropped and the
    monocular start (alignment, then the window batch) is redone on the keyframes from then on,
    retried at each keyframe as the first start is; the front end scales its map by the new
    start's scale. A smoother whose scale slips is no similarity of any trajectory the IMU
    explains. Off by default; ``euroc-mono-imu``: 0.01, where the delayed room-figure8 grid no
    longer diverges (loop-closed 4.6-76 mm against 19.7-9.1e4), though 5 of 9 delayed runs stay
    over 76 mm live (base 6), and every undelayed run measured is byte-identical (BENCHMARKS.md,
    reinit21 and the nineteenth session)."""
    mono_reinit_window_s: float = bounded(3.0, gt=0)
    """The smoother's keyframe positions of the last this many seconds are fitted for
    ``mono_reinit_residual_m`` (every ``mono_scale_check_every_s``, once they span 0.8 of it;
    the scale check keeps its own ``mono_scale_check_window_s``). Good runs: 0.1-2.3 mm over 3 s."""
    mono_reinit_max: int = bounded(3, ge=1)
    """At most this many such re-initialisations per run."""

    # --- smoother -------------------------------------------------------------------------------
    lag_s: float = bounded(1.0, gt=0)
    """Fixed-lag smoother window in seconds (states older than this are marginalised); 1 s is
    about 10 keyframes at the usual keyframe rate. Update cost grows ~linearly with it."""
    relinearize_threshold: float = bounded(0.05, ge=0)
    """iSAM2 relinearisation threshold (tangent-space units)."""
    extra_iterations: int = bounded(0, ge=0)
    """Extra smoother update() calls per keyframe (each one more Gauss-Newton step)."""
    pixel_sigma_px: float = bounded(1.0, gt=0)
    """Projection measurement standard deviation (undistorted pixels)."""
    huber_k: float = bounded(1.345, gt=0)
    """Huber threshold in standard deviations for visual factors."""
    landmark_model: str = "smart"
    """"projection": landmarks are variables with Huber projection factors per camera;
    "smart": one SmartProjectionRigFactor per landmark (stereo rig, landmark eliminated,
    rebuilt with each new observation; outliers by GTSAM's dynamic rejection threshold).
    Measured on the simulated world: same ATE, about half the CPU per keyframe."""
    right_camera_factors: bool = True
    """Add a projection factor for the right camera too (else it only helps triangulation)."""
    # bounds: a landmark seen by one keyframe constrains no pose
    min_keyframes_per_landmark: int = bounded(2, ge=2)
    """A landmark enters the smoother once this many keyframes in the window observed it."""
    max_landmarks_per_keyframe: int = bounded(200, ge=1)
    """Observations kept per keyframe (the first ones the front end sends)."""
    min_depth_m: float = bounded(0.1, gt=0, lt_field="max_depth_m")
    """Landmarks closer than this to a camera are not inserted / observations are dropped."""
    max_depth_m: float = bounded(60.0, gt=0)
    """Landmarks further than this from the keyframes that see them are not inserted."""
    outlier_reprojection_px: float = bounded(5.0, gt=0)
    """Observations with a reprojection error above this (against the current estimate) are
    rejected before insertion; landmarks with a mean error above it after optimisation are
    culled (no further observations)."""
    map_landmarks: bool = True
    """Landmarks seen again after they left the window (the front end found them in its map)
    come back as variables held by a prior at their last estimated position."""
    map_landmark_sigma_m: float = bounded(0.02, gt=0)
    """Standard deviation of that prior, metres."""
    max_map_landmarks_per_keyframe: int = bounded(100, ge=0)
    """Of them, observations taken per keyframe at most (each is a projection factor per
    camera, not one smart factor per landmark: this bounds the smoother's size)."""
    prior_pose_sigma_rad: float = bounded(0.01, gt=0)
    """Rotation sigma of the first/reset pose prior (yaw and position are gauge freedoms)."""
    prior_pose_sigma_m: float = bounded(0.01, gt=0)
    """Position sigma of the first/reset pose prior."""
    prior_velocity_sigma_m_s: float = bounded(0.1, gt=0)
    """Velocity sigma of the first/reset velocity prior."""
    prior_bias_gyro_sigma_rad_s: float = bounded(0.005, gt=0)
    """Gyro-bias sigma of the first/reset bias prior."""
    prior_bias_accel_sigma_m_s2: float = bounded(0.1, gt=0)
    """Accel-bias sigma of the first/reset bias prior."""
    no_imu_pose_sigma_m: float = bounded(0.05, gt=0)
    """Position sigma per keyframe of the VO relative-pose factor used when there is no IMU factor."""
    no_imu_pose_sigma_rad: float = bounded(0.02, gt=0)
    """Rotation sigma of that VO relative-pose factor."""
    no_imu_velocity_sigma_m_s: float = bounded(1.0, gt=0)
    """Sigma of the velocity random-walk factor used when there is no IMU factor."""

    # --- camera-IMU time offset (slam.backend.time_offset) --------------------------------------
    time_offset_online: bool = True
    """Estimate the camera-IMU time offset online (keyframe rotations against the gyro) and,
    once known to ``time_offset_apply_std_ms``, stamp every frame with it (the IMU's clock)."""
    time_offset_prior_sigma_ms: float = bounded(20.0, gt=0)
    """Prior on the offset around the calibration's (0 on top of it)."""
    time_offset_max_ms: float = bounded(50.0, gt=0, le=500)
    """Search range: an offset beyond +- this is reported ("beyond the bound"), never applied."""
    time_offset_window_s: float = bounded(30.0, gt=0)
    """Keyframe pairs of the last this many seconds are used. A camera with auto-exposure that
    stamps its images at the end of the exposure shows the scene at mid-exposure, an offset of
    minus half an exposure that moves with the light (-1 to -5 ms in ``slam synth --camera
    realistic``): set 4 s to follow it (room-aggressive with that timing and no blur,
    sequential, live / loop-closed ATE 15.9 / 6.0 mm with 30 s, 7.5 / 4.8 with 4 s; the clean
    suite's figures with 4 s are in BENCHMARKS.md, 2026-12-02/03, cam17)."""
    time_offset_apply_std_ms: float = bounded(0.5, gt=0)
    """The estimate is applied once its standard deviation is below this. On slow, smooth motion
    the spread is optimistic: the front end's keyframe rotations carry errors that are not
    independent from pair to pair, so on room-figure8 (zero offset) the estimate wanders by
    +-2-6 ms while it reports 0.7-1.0 ms (with ground-truth rotations the same estimator reports
    0.35 ms and is within 0.3 ms). With 1.0 it applied +3.8 ms there (loop-closed ATE 2.1 mm
    against 0.70 with it unapplied); fast motion gets below 0.05 ms (BENCHMARKS.md, "The online
    time offset's gate")."""
    time_offset_min_pairs: int = bounded(8, ge=3)
    """Keyframe pairs needed before estimating."""
    time_offset_hold_s: float = bounded(0.0, ge=0)
    """Once initialised and moving, keyframes wait (the front end runs on alone) until the offset
    is known, at most this long per run; then they are fused in the IMU clock. 0 (default):
    never wait. 1.5 s: set it for a rig whose offset is not known; at -30..+30 ms it keeps the
    ATE of fast motion within 1.3x of a zero-offset run (without it 4-14x). Off by default: at
    zero offset it cost room-figure8, room-loop and the hall 17-47 % of live ATE (slower
    motion: the offset is not known within the hold; BENCHMARKS.md, "Sequential runs
    deterministic with the time offset's hold"); a run interrupted while keyframes wait has
    no smoothed poses for them."""

    # --- divergence checks ----------------------------------------------------------------------
    max_velocity_m_s: float = bounded(20.0, gt=0)
    """A velocity norm above this is a divergence."""
    max_velocity_jump_m_s: float = bounded(2.0, gt=0)
    """Optimised velocity differing by more than this from the IMU prediction is a divergence."""
    max_bias_gyro_rad_s: float = bounded(0.5, gt=0)
    """A gyro bias norm above this is a divergence."""
    max_bias_accel_m_s2: float = bounded(2.0, gt=0)
    """An accel bias norm above this is a divergence."""
    max_position_jump_m: float = bounded(1.0, gt=0)
    """An optimised keyframe position farther than this from its prediction is a divergence."""

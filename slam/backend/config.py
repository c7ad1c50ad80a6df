"""Configuration of the visual-inertial back end (one dataclass, nested into ``SlamConfig``)."""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class BackendConfig:
    """Every tunable of the back end. Units are in the names; defaults suit EuRoC-grade IMUs."""

    # --- IMU sanitising -------------------------------------------------------------------------
    max_accel_m_s2: float = 16.0 * 9.81
    """Accelerometer saturation limit: samples with any |axis| above it are rejected."""
    max_gyro_rad_s: float = 35.0
    """Gyroscope saturation limit: samples with any |axis| above it are rejected."""
    imu_gap_warn_factor: float = 3.0
    """An interval longer than this many nominal sample periods is counted and warned about."""
    imu_gap_max_s: float = 0.1
    """Longest interval integrated across; between keyframes spanning a longer gap there is no
    IMU factor (the estimator runs on vision, with a weak VO relative-pose factor)."""
    imu_buffer_s: float = 30.0
    """IMU history kept (seconds before the newest keyframe) for integration and resets."""

    # --- initialisation -------------------------------------------------------------------------
    init_mode: str = "auto"
    """"auto" (still start if the IMU before the first keyframe is still, else moving start),
    "still" or "moving"."""
    still_window_s: float = 1.0
    """Length of IMU history that must be still for a still start."""
    still_smoothing_s: float = 0.1
    """Still test: readings are first averaged over this long (removes rotor vibration; on
    EuRoC V1_01 the raw accel-norm std is 0.2-0.3 m/s^2 while the vehicle stands still)."""
    still_accel_std_m_s2: float = 0.15
    """Still test: std of every smoothed accelerometer axis over the window below this."""
    still_gyro_std_rad_s: float = 0.015
    """Still test: std of every smoothed gyro axis over the window below this."""
    still_init_method: str = "kalman"
    """"kalman" (filterpy linear KF, the design card's tool) or "align" (scipy align_vectors on
    the mean accel); measured equal accuracy on EuRoC V1_01, "align" is ~50x cheaper."""
    moving_init_keyframes: int = 10
    """Minimum keyframes (VO poses + IMU between them) for the moving-start alignment; up to
    three times as many (the newest) are used."""
    moving_init_min_span_s: float = 1.5
    """Minimum time span of the keyframes used for the moving-start alignment."""
    moving_init_max_gravity_error: float = 0.5
    """Reject the unconstrained gravity solution if | |g| - g0 | exceeds this (m/s^2) and retry
    with more keyframes."""

    # --- smoother -------------------------------------------------------------------------------
    lag_s: float = 1.0
    """Fixed-lag smoother window in seconds (states older than this are marginalised); 1 s is
    about 10 keyframes at the usual keyframe rate. Update cost grows ~linearly with it."""
    relinearize_threshold: float = 0.05
    """iSAM2 relinearisation threshold (tangent-space units)."""
    extra_iterations: int = 0
    """Extra smoother update() calls per keyframe (each one more Gauss-Newton step)."""
    pixel_sigma_px: float = 1.0
    """Projection measurement standard deviation (undistorted pixels)."""
    huber_k: float = 1.345
    """Huber threshold in standard deviations for visual factors."""
    landmark_model: str = "smart"
    """"projection": landmarks are variables with Huber projection factors per camera;
    "smart": one SmartProjectionRigFactor per landmark (stereo rig, landmark eliminated,
    rebuilt with each new observation; outliers by GTSAM's dynamic rejection threshold).
    Measured on the simulated world: same ATE, about half the CPU per keyframe."""
    right_camera_factors: bool = True
    """Add a projection factor for the right camera too (else it only helps triangulation)."""
    min_keyframes_per_landmark: int = 2
    """A landmark enters the smoother once this many keyframes in the window observed it."""
    max_landmarks_per_keyframe: int = 200
    """Observations kept per keyframe (the first ones the front end sends)."""
    min_depth_m: float = 0.1
    """Landmarks closer than this to a camera are not inserted / observations are dropped."""
    max_depth_m: float = 60.0
    """Landmarks further than this from the keyframes that see them are not inserted."""
    outlier_reprojection_px: float = 5.0
    """Observations with a reprojection error above this (against the current estimate) are
    rejected before insertion; landmarks with a mean error above it after optimisation are
    culled (no further observations)."""
    prior_pose_sigma_rad: float = 0.01
    """Rotation sigma of the first/reset pose prior (yaw and position are gauge freedoms)."""
    prior_pose_sigma_m: float = 0.01
    """Position sigma of the first/reset pose prior."""
    prior_velocity_sigma_m_s: float = 0.1
    """Velocity sigma of the first/reset velocity prior."""
    prior_bias_gyro_sigma_rad_s: float = 0.005
    """Gyro-bias sigma of the first/reset bias prior."""
    prior_bias_accel_sigma_m_s2: float = 0.1
    """Accel-bias sigma of the first/reset bias prior."""
    no_imu_pose_sigma_m: float = 0.05
    """Position sigma per keyframe of the VO relative-pose factor used when there is no IMU factor."""
    no_imu_pose_sigma_rad: float = 0.02
    """Rotation sigma of that VO relative-pose factor."""
    no_imu_velocity_sigma_m_s: float = 1.0
    """Sigma of the velocity random-walk factor used when there is no IMU factor."""

    # --- divergence checks ----------------------------------------------------------------------
    max_velocity_m_s: float = 20.0
    """A velocity norm above this is a divergence."""
    max_velocity_jump_m_s: float = 2.0
    """Optimised velocity differing by more than this from the IMU prediction is a divergence."""
    max_bias_gyro_rad_s: float = 0.5
    """A gyro bias norm above this is a divergence."""
    max_bias_accel_m_s2: float = 2.0
    """An accel bias norm above this is a divergence."""
    max_position_jump_m: float = 1.0
    """An optimised keyframe position farther than this from its prediction is a divergence."""

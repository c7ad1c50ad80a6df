"""The synthetic sequence: a lazily rendered :class:`Sequence` with exact ground truth.

``make_synthetic_sequence(profile="figure8", duration_s=..., seed=0)`` builds the motion, the
scene around it (boxes kept away from the path), the EuRoC-like stereo calibration and the IMU
stream; images are rendered on demand in ``frame(i)`` (a 20-minute sequence never lives in
memory). Ground truth is world_from_body at the IMU times (200 Hz), and at each image's
mid-exposure time where the camera has an exposure (blur). Time starts at 0 ns for
profiles, and at the file's first pose for ``trajectory_file``.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Iterator
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from datasets.rigs import FRAME_RATE_HZ, euroc_like_calibration
from datasets.sequence import ImuArrays, Sequence
from datasets.synth.camera_model import (
    CameraEffects,
    ExposureSchedule,
    exposure_schedule,
    sensor_image,
    vignetting_map,
)
from datasets.synth.imu_sim import (
    ImuDistortion,
    ImuEffects,
    read_imu_csv,
    real_imu_errors_on_motion,
    simulate_imu,
)
from datasets.synth.render import BAND_ROWS, StereoRenderer
from datasets.synth.scene import Scene, build_scene, room_around_path
from datasets.synth.trajectories import (
    Motion,
    MotionSamples,
    ProfileMotion,
    SplineMotion,
    make_profile,
    motion_from_file,
)
from slam.core.calibration import (
    Calibration,
    ImuCalibration,
)
from slam.core.errors import InputError
from slam.core.geometry import rotation_angle_rad
from slam.core.messages import StereoFrame, mid_exposure_ns
from slam.core.trajectory import Trajectory

if TYPE_CHECKING:
    from datasets.synth.imu_check import AccelScale, GyroAgreement

PREFETCH_FRAMES = 2  # frames rendered ahead by iter_frames()
ROLLING_SHUTTER_BAND_ROWS = 16  # rows rendered at one time with a rolling shutter
MAX_TIME_OFFSET_NS = 500_000_000  # injected camera-IMU offsets: +-0.5 s
BLUR_NEAR_DEPTH_M = 1.0  # depth assumed when turning translation into image motion (sub-frames)


@dataclass(frozen=True)
class SynthOptions:
    """What a synthetic sequence was made with (saved alongside it for reproducibility)."""

    profile: str = "figure8"
    duration_s: float | None = None  # None: the profile's default (or the whole file)
    seed: int = 0  # noise seed (IMU noise, pixel noise)
    scene_seed: int = 0  # textures and boxes
    imu_noise: bool = True
    blackout: tuple[float, float] | None = None  # (start_s, duration_s) of black frames
    moving_start: bool = False
    aliasing: bool = False  # identical boxes and long walls (perceptual aliasing)
    pixel_noise_std: float = 0.0  # grey levels, Gaussian
    trajectory_file: str | None = None
    imu_csv: str | None = None
    imu_csv_on_trajectory: bool = False  # the trajectory's readings + the csv's errors
    camera: CameraEffects = CameraEffects()
    imu_effects: ImuEffects = ImuEffects()
    time_offset_ns: int = 0  # an image stamped t shows the scene at IMU time t + offset
    calib_rotation_error_deg: tuple[float, float, float] | None = None  # rotation vector


class SyntheticSequence(Sequence):
    """A rendered-on-demand sequence with exact ground truth, depth and scene geometry."""

    def __init__(
        self,
        *,
        name: str,
        calibration: Calibration,
        motion: Motion,
        motion_t0_s: float,
        scene: Scene,
        frame_times_ns: np.ndarray,
        imu: ImuArrays,
        ground_truth: Trajectory,
        options: SynthOptions,
        imu_gyro_bias_rad_s: np.ndarray | None = None,
        imu_accel_bias_m_s2: np.ndarray | None = None,
        true_calibration: Calibration | None = None,
        imu_distortion: ImuDistortion | None = None,
    ) -> None:
        super().__init__(name=name, calibration=calibration, ground_truth=ground_truth)
        # the rig as it is (rendering); ``calibration`` is what the file says (it may be wrong)
        self.true_calibration = true_calibration or calibration
        self.imu_distortion = imu_distortion
        self.motion = motion
        self.motion_t0_s = motion_t0_s  # motion time of t_ns = frame_times_ns[0] (or imu[0])
        self.t0_ns = int(min(frame_times_ns[0], imu.t_ns[0] if len(imu) else frame_times_ns[0]))
        self.scene = scene
        self.options = options
        self.imu_gyro_bias_rad_s = imu_gyro_bias_rad_s
        self.imu_accel_bias_m_s2 = imu_accel_bias_m_s2
        self._frame_times_ns = np.asarray(frame_times_ns, dtype=np.int64)
        self._imu = imu
        self._renderer: StereoRenderer | None = None
        self.exposure: ExposureSchedule = exposure_schedule(
            options.camera,
            self.motion_time_s(self._frame_times_ns + options.time_offset_ns),
            options.seed,
        )
        self._exposures_ns = (
            np.round(self.exposure.exposure_s * 1e9).astype(np.int64)
            if options.camera.blurs
            else None
        )
        if self._exposures_ns is not None and self.ground_truth is not None:
            self.ground_truth = self._ground_truth_at_image_times(self.ground_truth)
        self._vignetting: list[np.ndarray] | None = None
        self.gyro_agreement: GyroAgreement | None = None  # a real IMU against the motion
        self.accel_scale: AccelScale | None = None  # the same, its accelerometer

    def __getstate__(self) -> dict:
        state = self.__dict__.copy()
        state["_renderer"] = None  # rebuilt on demand (pixel rays), keeps pickles small
        state["_vignetting"] = None
        return state

    # --- Sequence interface ------------------------------------------------------------------
    def frame_times_ns(self) -> np.ndarray:
        return self._frame_times_ns

    def imu(self) -> ImuArrays:
        return self._imu

    def exposures_ns(self) -> np.ndarray | None:
        """The exposure each image integrates over (motion blur over ``[stamp - E, stamp]``),
        ns; None when images are instantaneous (no blur: they show the scene at the stamp)."""
        return self._exposures_ns

    def frame(self, index: int) -> StereoFrame:
        t_ns = int(self._frame_times_ns[index])
        exposure_ns = 0 if self._exposures_ns is None else int(self._exposures_ns[index])
        if self.is_blacked_out(index):
            shape = (
                self.calibration.cam0.intrinsics.height,
                self.calibration.cam0.intrinsics.width,
            )
            black = np.zeros(shape, np.uint8)
            return StereoFrame(t_ns, black, black.copy(), index, exposure_ns=exposure_ns)
        if self.options.camera.active:
            images = self._camera_images(index)
        else:
            outs = self.renderer.render(self.world_from_body_at(self.content_time_ns(index)))
            images = [o.image for o in outs]
        if self.options.pixel_noise_std > 0:
            images = [self._add_pixel_noise(img, index, k) for k, img in enumerate(images)]
        right = images[1] if len(images) > 1 else None
        return StereoFrame(t_ns, images[0], right, index, exposure_ns=exposure_ns)

    def content_time_ns(self, index: int) -> int:
        """IMU-clock time the image of frame ``index`` shows (the end of its exposure): its
        stamp plus the injected camera-IMU time offset."""
        return int(self._frame_times_ns[index]) + int(self.options.time_offset_ns)

    def _camera_images(self, index: int) -> list[np.ndarray]:
        """Both cameras through :mod:`datasets.synth.camera_model`: radiance averaged over
        sub-frames spread over the exposure window (and row bands at their own times with a
        rolling shutter), scaled by brightness, vignetting and stereo gain, plus sensor noise."""
        fx = self.options.camera
        exposure_s = float(self.exposure.exposure_s[index]) if fx.blurs else 0.0
        brightness = float(self.exposure.brightness[index])
        gain = float(self.exposure.gain[index])
        n_sub = self.subframes(index)
        t_end_ns = self.content_time_ns(index)
        height = self.true_calibration.cam0.intrinsics.height
        band_rows = ROLLING_SHUTTER_BAND_ROWS if fx.line_delay_s > 0 else BAND_ROWS
        centres = np.arange(0, height, band_rows) + (band_rows - 1) / 2.0
        band_offset_s = (np.minimum(centres, height - 1) - (height - 1) / 2.0) * fx.line_delay_s
        sub_offset_s = -exposure_s * (np.arange(n_sub) + 0.5) / n_sub
        t_s = self.motion_time_s(t_end_ns)[None, None] + sub_offset_s[:, None] + band_offset_s
        bodies = self.motion.sample(t_s.ravel()).world_from_body()
        bodies = bodies.reshape(n_sub, len(band_offset_s), 4, 4)
        if self._vignetting is None:
            self._vignetting = [
                vignetting_map(fx, cam.intrinsics) for cam in self.true_calibration.cameras
            ]
        images = []
        for c, renderer in enumerate(self.renderer.cameras):
            radiance = np.zeros((height, renderer.width), np.float32)
            for j in range(n_sub):
                radiance += renderer.render_radiance(
                    bodies[j] @ renderer.camera.body_from_cam, band_rows
                )
            radiance *= np.float32(1.0 / n_sub)
            scale = self._vignetting[c] * np.float32(brightness * (fx.stereo_gain if c else 1.0))
            rng = np.random.default_rng([self.options.seed, index, c, 5])
            images.append(sensor_image(radiance, scale, gain, fx, rng))
        return images

    def subframes(self, index: int) -> int:
        """Sub-frames rendered over frame ``index``'s exposure: enough that the image moves by
        at most ``subframe_spacing_px`` between two (rotation, plus translation seen at
        ``BLUR_NEAR_DEPTH_M``), capped at ``max_subframes``."""
        fx = self.options.camera
        if not fx.blurs:
            return 1
        exposure_s = float(self.exposure.exposure_s[index])
        t_end = float(self.motion_time_s(self.content_time_ns(index)))
        ends = self.motion.sample(np.array([t_end - exposure_s, t_end])).world_from_body()
        cam = self.true_calibration.cam0
        a, b = ends[0] @ cam.body_from_cam, ends[1] @ cam.body_from_cam
        angle = rotation_angle_rad(a[:3, :3].T @ b[:3, :3])
        shift = float(np.linalg.norm(a[:3, 3] - b[:3, 3])) / BLUR_NEAR_DEPTH_M
        motion_px = max(cam.intrinsics.fx, cam.intrinsics.fy) * (angle + shift)
        return int(np.clip(np.ceil(motion_px / fx.subframe_spacing_px), 1, fx.max_subframes))

    def iter_frames(self) -> Iterator[StereoFrame]:
        """Frames in order, rendering up to ``PREFETCH_FRAMES`` ahead in a worker thread (numpy
        and cv2.remap release the GIL, so rendering overlaps the consumer's work)."""
        n = self.num_frames
        with ThreadPoolExecutor(max_workers=1, thread_name_prefix="synth-render") as pool:
            pending: deque[Future[StereoFrame]] = deque()
            for i in range(min(PREFETCH_FRAMES, n)):
                pending.append(pool.submit(self.frame, i))
            for i in range(n):
                frame = pending.popleft().result()
                if i + PREFETCH_FRAMES < n:
                    pending.append(pool.submit(self.frame, i + PREFETCH_FRAMES))
                yield frame

    # --- ground truth -----------------------------------------------------------------------
    @property
    def renderer(self) -> StereoRenderer:
        if self._renderer is None:
            self._renderer = StereoRenderer(self.scene, self.true_calibration.cameras)
        return self._renderer

    def motion_time_s(self, t_ns: np.ndarray | int) -> np.ndarray:
        """Motion time (s) of sequence timestamps."""
        return self.motion_t0_s + (np.asarray(t_ns, dtype=np.int64) - self.t0_ns) * 1e-9

    def world_from_body_at(self, t_ns: int) -> np.ndarray:
        """Exact 4x4 world_from_body at any time (not only ground-truth samples)."""
        return self.motion.sample(np.array([self.motion_time_s(t_ns)])).world_from_body()[0]

    def world_from_cam(self, index: int, cam: int = 0) -> np.ndarray:
        """Exact 4x4 world_from_cam of frame ``index`` (at the time its image shows, through
        the true extrinsics)."""
        t_ns = self.content_time_ns(index)
        return self.world_from_body_at(t_ns) @ self.true_calibration.cameras[cam].body_from_cam

    def _ground_truth_at_image_times(self, grid: Trajectory) -> Trajectory:
        """``grid`` (the IMU-rate ground truth) plus the exact pose at each image's
        mid-exposure time, the stamp the player gives a frame whose exposure is recorded
        (:func:`slam.core.messages.mid_exposure_ns`). Those times fall between the 5 ms grid
        points; without them nearest-pose association (``slam eval``'s and evo's) pairs an
        estimate with a ground-truth pose up to 2.5 ms away, an error the estimate does not
        have (up to 6 mm at 2.5 m/s)."""
        assert self._exposures_ns is not None
        image_t_ns = mid_exposure_ns(
            self._frame_times_ns + int(self.options.time_offset_ns), self._exposures_ns
        )
        t_ns = np.union1d(grid.t_ns, image_t_ns)
        t_ns = t_ns[(t_ns >= grid.t_ns[0]) & (t_ns <= grid.t_ns[-1])]
        poses = self.motion.sample(self.motion_time_s(t_ns)).world_from_body()
        return Trajectory.from_matrices(t_ns, poses)

    def ground_truth_state(self) -> MotionSamples:
        """Full true state at the ground-truth times: positions, world velocities and
        accelerations, rotations, body angular velocities (the true IMU biases are in
        ``imu_gyro_bias_rad_s`` / ``imu_accel_bias_m_s2``)."""
        assert self.ground_truth is not None
        return self.motion.sample(self.motion_time_s(self.ground_truth.t_ns))

    def depth(self, index: int, cam: int = 0) -> np.ndarray:
        """Ground-truth depth (H, W) float32: z in the camera frame, metres (every pixel hits
        a surface; blackout does not affect depth)."""
        return self.renderer.cameras[cam].render_depth(self.world_from_cam(index, cam))

    def is_blacked_out(self, index: int) -> bool:
        if self.options.blackout is None:
            return False
        start_s, dur_s = self.options.blackout
        t_rel = (int(self._frame_times_ns[index]) - self.t0_ns) * 1e-9
        return start_s <= t_rel < start_s + dur_s

    def scene_mesh(self) -> tuple[np.ndarray, np.ndarray]:
        """Vertices (V, 3) and triangles (T, 3) of the true scene surface (world frame)."""
        return self.scene.mesh()

    def sample_surface_points(self, n: int, seed: int = 0) -> np.ndarray:
        """``n`` points uniformly on the true visible surface (world frame)."""
        pts = self.scene.sample_surface_points(n, seed=seed)
        assert isinstance(pts, np.ndarray)
        return pts

    def _add_pixel_noise(self, image: np.ndarray, index: int, cam: int) -> np.ndarray:
        rng = np.random.default_rng([self.options.seed, index, cam])
        noisy = rng.standard_normal(image.shape, dtype=np.float32)
        noisy *= np.float32(self.options.pixel_noise_std)
        noisy += image
        return np.clip(np.round(noisy), 0, 255).astype(np.uint8)


def _camera_centres(motion: Motion, t_s: np.ndarray, calib: Calibration) -> np.ndarray:
    poses = motion.sample(t_s).world_from_body()
    centres = [poses[:, :3, 3]]
    for cam in calib.cameras:
        centres.append(poses[:, :3, :3] @ cam.body_from_cam[:3, 3] + poses[:, :3, 3])
    return np.concatenate(centres)


def make_synthetic_sequence(
    profile: str = "figure8",
    duration_s: float | None = None,
    seed: int = 0,
    *,
    imu_noise: bool = True,
    blackout: tuple[float, float] | None = None,
    moving_start: bool = False,
    aliasing: bool = False,
    pixel_noise_std: float = 0.0,
    scene_seed: int = 0,
    trajectory_file: str | None = None,
    imu_csv: str | None = None,
    imu_csv_on_trajectory: bool = False,
    imu_calibration: ImuCalibration | None = None,
    gyro_bias0_rad_s: np.ndarray | None = None,
    accel_bias0_m_s2: np.ndarray | None = None,
    camera: CameraEffects | None = None,
    imu_effects: ImuEffects | None = None,
    time_offset_ns: int = 0,
    calib_rotation_error_deg: tuple[float, float, float] | None = None,
) -> SyntheticSequence:
    """Build a synthetic stereo-inertial sequence (rendering happens lazily, per frame).

    ``profile``: ``figure8``, ``loop``, ``aggressive`` or ``hall`` (see
    :func:`datasets.synth.trajectories.make_profile`); ignored when ``trajectory_file`` (TUM or
    EuRoC ground truth) is given. ``imu_csv``: a real EuRoC ``imu0/data.csv`` used instead of
    the simulated IMU (it must share the trajectory file's clock); ``imu_csv_on_trajectory``:
    the trajectory's exact readings plus that IMU's bias drift and noise instead
    (:func:`~datasets.synth.imu_sim.real_imu_errors_on_motion`). ``blackout``: (start_s,
    duration_s) relative to the first frame, frames in it are black. ``seed`` drives the IMU
    and pixel noise; ``scene_seed`` the textures and box sizes.

    A real rig: ``camera`` (:class:`~datasets.synth.camera_model.CameraEffects`: blur,
    auto-exposure, vignetting, stereo gain, sensor noise, rolling shutter), ``imu_effects``
    (:class:`~datasets.synth.imu_sim.ImuEffects`: vibration, scale, misalignment),
    ``time_offset_ns`` (an image stamped t shows the scene at IMU time t + offset; the file's
    calibration says 0) and ``calib_rotation_error_deg`` (a rotation vector, degrees: the
    file's body_from_cam rotations are this rotation off the rig's true ones, which render).
    """
    options = SynthOptions(
        profile=profile if trajectory_file is None else "file",
        duration_s=duration_s,
        seed=seed,
        scene_seed=scene_seed,
        imu_noise=imu_noise,
        blackout=blackout,
        moving_start=moving_start,
        aliasing=aliasing,
        pixel_noise_std=pixel_noise_std,
        trajectory_file=trajectory_file,
        imu_csv=imu_csv,
        imu_csv_on_trajectory=imu_csv_on_trajectory,
        camera=camera or CameraEffects(),
        imu_effects=imu_effects or ImuEffects(),
        time_offset_ns=int(time_offset_ns),
        calib_rotation_error_deg=calib_rotation_error_deg,
    )
    if duration_s is not None and duration_s <= 0:
        raise InputError(f"duration must be positive, got {duration_s} s")
    options.camera.validate()
    options.imu_effects.validate()
    if abs(time_offset_ns) > MAX_TIME_OFFSET_NS:
        raise InputError(
            f"time offset {time_offset_ns * 1e-6:.1f} ms is beyond +-{MAX_TIME_OFFSET_NS * 1e-6:.0f} ms"
        )
    if imu_csv is not None and (options.imu_effects.active):
        raise InputError("IMU effects need the simulated IMU (not --imu-csv)")
    if imu_csv_on_trajectory and imu_csv is None:
        raise InputError("--imu-csv-on-trajectory needs --imu-csv (the IMU whose errors to keep)")
    if imu_csv is not None and trajectory_file is None:
        raise InputError("--imu-csv needs --from-trajectory (the IMU must match a trajectory)")
    calib = euroc_like_calibration(imu_calibration)
    given_calib = calib
    if calib_rotation_error_deg is not None:
        given_calib = _rotated_extrinsics(calib, np.radians(calib_rotation_error_deg))
    motion: Motion
    if trajectory_file is not None:
        motion = motion_from_file(trajectory_file)
        assert isinstance(motion, SplineMotion)
        span_s = motion.t_end_s - motion.t_start_s
        dur = span_s if duration_s is None else min(duration_s, span_s)
        t0_ns = motion.t0_ns
        name = f"synth-{motion.name}"
        kind = "room"
        path_t = np.arange(0.0, dur, 0.05)
        centres = _camera_centres(motion, path_t, calib)
        room = room_around_path(centres)
    else:
        motion = make_profile(profile, moving_start=moving_start)
        assert isinstance(motion, ProfileMotion)
        dur = motion.default_duration_s if duration_s is None else float(duration_s)
        t0_ns = 0
        name = f"synth-{profile}"
        kind = motion.kind
        path_t = np.arange(0.0, max(dur, 150.0), 0.05)  # the scene must not depend on duration
        centres = _camera_centres(motion, path_t, calib)
        room = None
    scene = build_scene(kind, room=room, path_m=centres, aliasing=aliasing, seed=scene_seed)
    dur_ns = int(round(dur * 1e9))
    frame_step = int(round(1e9 / FRAME_RATE_HZ))
    imu_step = int(round(1e9 / calib.imu.rate_hz)) if calib.imu else 5_000_000
    frame_times = t0_ns + np.arange(0, dur_ns + 1, frame_step, dtype=np.int64)
    imu_times = t0_ns + np.arange(0, dur_ns + 1, imu_step, dtype=np.int64)
    assert calib.imu is not None
    bg = ba = None
    distortion = None
    if imu_csv is not None:
        imu = read_imu_csv(imu_csv, int(frame_times[0]), int(frame_times[-1]))
        if len(imu) == 0:
            raise InputError(
                f"{imu_csv}: no IMU samples within the trajectory's time span; "
                "the IMU csv and the trajectory file must share one clock"
            )
        if imu_csv_on_trajectory:
            imu = real_imu_errors_on_motion(motion, imu, t0_ns, calib.imu, seed)
    else:
        sim = simulate_imu(
            motion,
            imu_times,
            0.0,
            calib.imu,
            noise=imu_noise,
            seed=seed,
            gyro_bias0_rad_s=gyro_bias0_rad_s,
            accel_bias0_m_s2=accel_bias0_m_s2,
            effects=imu_effects,
        )
        imu, bg, ba = sim.arrays, sim.gyro_bias_rad_s, sim.accel_bias_m_s2
        distortion = sim.distortion
    gt_samples = motion.sample((imu_times - t0_ns) * 1e-9)
    ground_truth = Trajectory.from_matrices(imu_times, gt_samples.world_from_body())
    seq = SyntheticSequence(
        name=name,
        calibration=given_calib,
        true_calibration=calib,
        imu_distortion=distortion,
        motion=motion,
        motion_t0_s=0.0,
        scene=scene,
        frame_times_ns=frame_times,
        imu=imu,
        ground_truth=ground_truth,
        options=options,
        imu_gyro_bias_rad_s=bg,
        imu_accel_bias_m_s2=ba,
    )
    if imu_csv is not None:
        _check_real_imu(seq, motion, imu, t0_ns)
    return seq


def _check_real_imu(seq: SyntheticSequence, motion: Motion, imu: ImuArrays, t0_ns: int) -> None:
    """Warn when the real IMU's gyro and the trajectory the images follow disagree
    (:mod:`datasets.synth.imu_check`); the figure is kept in ``seq.gyro_agreement``."""
    from datasets.synth.imu_check import (
        MAX_MEDIAN_DISAGREEMENT_DEG,
        accel_scale_agreement,
        gyro_agreement,
    )

    agreement = gyro_agreement(motion, imu, t0_ns)
    seq.gyro_agreement = agreement
    assert seq.calibration.imu is not None
    seq.accel_scale = accel_scale_agreement(motion, imu, t0_ns, seq.calibration.imu.gravity_m_s2)
    if agreement is not None and agreement.median_deg > MAX_MEDIAN_DISAGREEMENT_DEG:
        seq.warn(
            f"the IMU and the trajectory disagree: the gyro integrated over "
            f"{agreement.window_s:g} s turns {agreement.median_deg:.2f} deg (median; "
            f"{agreement.max_deg:.2f} max) away from the trajectory's rotation, above "
            f"{MAX_MEDIAN_DISAGREEMENT_DEG} deg: the images follow the trajectory, the IMU the "
            "real motion, and visual-inertial accuracy is bounded by their disagreement (is the "
            "trajectory's orientation accurate? EuRoC V1_01: use OpenVINS's recomputed ground truth)"
        )


def _rotated_extrinsics(calib: Calibration, rotvec_rad: np.ndarray) -> Calibration:
    """The calibration with every body_from_cam rotated by ``exp(rotvec)`` about the body
    origin (the whole rig mis-calibrated against the IMU; the stereo pair stays consistent)."""
    from dataclasses import replace

    from slam.core.geometry import make_transform, so3_exp

    err = make_transform(so3_exp(np.asarray(rotvec_rad, dtype=np.float64)), np.zeros(3))
    cams = tuple(replace(c, body_from_cam=err @ c.body_from_cam) for c in calib.cameras)
    return replace(calib, cameras=cams)

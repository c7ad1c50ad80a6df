"""Every object that crosses a thread or process boundary.

Rules: frozen dataclasses, an integer ``t_ns`` (nanoseconds, sensor clock), SI units in the field
names, picklable. Arrays are never mutated after construction.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, TypeVar

import numpy as np

if TYPE_CHECKING:  # the loop closer's own type; only its instances travel
    from slam.loop.store import KeyframeDescription


@dataclass(frozen=True, eq=False)
class ImuSample:
    """One IMU reading in the IMU (= body) frame."""

    t_ns: int
    gyro_rad_s: np.ndarray  # (3,) angular velocity, rad/s
    accel_m_s2: np.ndarray  # (3,) specific force, m/s^2 (gravity included, +9.81 up when still)


IntOrArray = TypeVar("IntOrArray", int, np.ndarray)


@dataclass(frozen=True, eq=False)
class StereoFrame:
    """A (possibly mono) camera frame, images as 8-bit grey, time in the IMU clock."""

    t_ns: int
    left: np.ndarray  # (H, W) uint8, cam0
    right: np.ndarray | None  # (H, W) uint8, cam1, or None for mono
    index: int = -1  # frame number within the sequence, -1 when unknown
    time_offset_ns: int = 0  # added to the camera stamp by the player (online time offset)
    exposure_ns: int = 0
    """The exposure's duration, ns (0: unknown). A reader's ``t_ns`` is the end of the
    exposure (the usual driver stamp); the image shows the scene as it was at its middle, where
    the player restamps it (``player.mid_exposure``, :func:`slam.runtime.player.at_mid_exposure`)."""

    @property
    def mid_exposure_ns(self) -> int:
        """The time its image shows: :func:`mid_exposure_ns` of its stamp and exposure."""
        return int(mid_exposure_ns(self.t_ns, self.exposure_ns))


def mid_exposure_ns(t_ns: IntOrArray, exposure_ns: IntOrArray) -> IntOrArray:
    """The middle of an exposure that ends at ``t_ns`` (an unknown exposure, 0: ``t_ns``).

    The scene moves while the shutter is open, and the image, blurred or not, shows it on
    average at the middle: every tool that pairs an image with a pose or an IMU reading
    (the player, ``slam calib check``, ``slam fuse``) uses this time, not the driver's stamp."""
    return t_ns - exposure_ns // 2


SensorMessage = ImuSample | StereoFrame


@dataclass(frozen=True, eq=False)
class Keyframe:
    """A keyframe from the front end, with its landmark observations.

    Pixel coordinates are *undistorted* pixels of the pinhole model with the camera's own K
    (``CameraIntrinsics.K``, distortion removed), so the back end can use plain Cal3_S2
    projection factors. ``pixels_right_undist`` rows are NaN where stereo matching failed.
    ``world_from_body_vo`` is the front end's (VO or IMU-propagated) estimate: an initial guess.
    """

    t_ns: int
    keyframe_id: int
    frame_index: int
    segment_id: int  # map segment; a new one starts after each unrecovered tracking loss
    world_from_body_vo: np.ndarray  # (4, 4)
    landmark_ids: np.ndarray  # (N,) int64, ids unique over the run
    pixels_left_undist: np.ndarray  # (N, 2) float64
    pixels_right_undist: np.ndarray  # (N, 2) float64, NaN where no stereo match
    points_world_vo: np.ndarray  # (N, 3) front-end landmark positions (initial guesses)
    image_left: np.ndarray  # (H, W) uint8, for the mapper and the loop closer
    image_right: np.ndarray | None
    metric: bool = True
    """False for a monocular front end's keyframes before the back end fixed the scale: its
    VO poses and points are up to scale (the back end's alignment uses them; the loop closer
    and the mapper skip them)."""
    time_offset_ns: int = 0  # its frame's: t_ns minus this is the camera's (mid-exposure) stamp
    previous_keyframe_id: int = -1
    # that keyframe's pose in this one's VO frame (moved by the corrections since), or None
    previous_keyframe_world_from_body: np.ndarray | None = None


@dataclass(frozen=True)
class TimeOffsetState:
    """The back end's online camera-IMU time offset (``slam.backend.time_offset``): an image
    stamped t shows IMU time t + offset, on top of the calibration's offset."""

    estimate_ns: float
    std_ns: float  # -1 while unknown
    applied_ns: int  # what the player adds to frame stamps now
    pairs: int  # keyframe pairs in the estimation window
    status: str  # "waiting for motion", "too little motion", "applied", "beyond the bound"


@dataclass(frozen=True, eq=False)
class ImuIntrinsics:
    """Correction matrices of an IMU's raw readings: ``calibrated = gyro_matrix @ raw_gyro``,
    ``calibrated = accel_matrix @ raw_accel`` (per-axis scale and axis misalignment), applied
    before the biases are taken off. Estimated online by the back end
    (``slam.backend.imu_intrinsics``) and applied by every ``slam.imu_buffer.ImuBuffer``
    reading of the readings (``set_intrinsics``)."""

    gyro_matrix: np.ndarray  # (3, 3), dimensionless
    accel_matrix: np.ndarray  # (3, 3), dimensionless

    @staticmethod
    def identity() -> ImuIntrinsics:
        return ImuIntrinsics(np.eye(3), np.eye(3))

    @property
    def is_identity(self) -> bool:
        return bool(np.array_equal(self.gyro_matrix, np.eye(3))) and bool(
            np.array_equal(self.accel_matrix, np.eye(3))
        )


@dataclass(frozen=True, eq=False)
class Estimate:
    """An immutable snapshot the back end publishes; the front end reads it without waiting.

    ``world_from_body`` / velocity / biases are for keyframe ``keyframe_id`` at ``t_ns``.
    ``keyframe_poses`` maps keyframe id -> world_from_body for the keyframes in the window
    (and any corrected by loop closure). Landmarks are the optimised positions in the window.
    """

    t_ns: int
    keyframe_id: int
    initialized: bool  # False until gravity/biases (VIO) or the first keyframe (VO) are known
    world_from_body: np.ndarray  # (4, 4)
    velocity_world_m_s: np.ndarray  # (3,)
    bias_gyro_rad_s: np.ndarray  # (3,)
    bias_accel_m_s2: np.ndarray  # (3,)
    keyframe_poses: dict[int, np.ndarray]
    landmark_ids: np.ndarray  # (M,) int64
    landmark_positions_world: np.ndarray  # (M, 3)
    map_generation: int = 0  # increments when a loop correction moves the whole map
    vo_scale: float = 1.0
    """Monocular: metres per unit of the front end's VO frame, found at initialisation. The
    front end scales its map by it (camera centres and landmarks about the VO origin,
    ``slam.core.geometry.scale_body_pose``) before it adopts the back end's world."""
    restarts: int = 0
    """Monocular: how many times the start was redone (``backend.mono_reinit_residual_m``).
    An estimate with a new count carries that start's ``vo_scale``, metres per unit of the front
    end's (already reframed) map: the front end scales its map by it again."""
    time_offset: TimeOffsetState | None = None  # the online camera-IMU offset (None: not run)
    imu_intrinsics: ImuIntrinsics | None = None
    """The IMU correction matrices applied in the back end (None: none estimated yet or the
    estimation is off); the front end applies the same to its readings."""

    @staticmethod
    def pose_only(
        t_ns: int,
        keyframe_id: int,
        world_from_body: np.ndarray,
        initialized: bool,
        map_generation: int = 0,
    ) -> Estimate:
        """An estimate of a pose alone: at rest, zero biases, no window keyframes or landmarks."""
        return Estimate(
            t_ns=t_ns,
            keyframe_id=keyframe_id,
            initialized=initialized,
            world_from_body=world_from_body,
            velocity_world_m_s=np.zeros(3),
            bias_gyro_rad_s=np.zeros(3),
            bias_accel_m_s2=np.zeros(3),
            keyframe_poses={},
            landmark_ids=np.zeros(0, np.int64),
            landmark_positions_world=np.zeros((0, 3)),
            map_generation=map_generation,
        )


@dataclass(frozen=True, eq=False)
class TrackingResult:
    """What the front end made of one frame: the pose (or the lack of one) and its features.

    ``state`` is one of "init" (a new map segment started here), "tracking", "lost",
    "relocalised" (found again in the existing map after a loss: the segment continues),
    "recovered" (tracking restarted at the IMU dead-reckoned pose: the segment continues).
    ``world_from_body`` is None when the frame could not be tracked: the trajectory marks the
    gap instead of inventing a pose. It is the odometry (smooth, never jumps);
    ``map_from_body`` the same pose in the loop-corrected map as known when the result was
    published (the latest :class:`LoopCorrection`'s ``map_from_odom`` of its segment applied;
    equal to the odometry before any loop). ``map_jump_m`` / ``map_jump_deg``: on the first
    result after a new correction, how far that correction moved this frame's map pose.
    """

    t_ns: int
    frame_index: int
    state: str
    segment_id: int
    world_from_body: np.ndarray | None  # (4, 4)
    is_keyframe: bool
    keyframe_id: int  # -1 unless is_keyframe
    num_tracked: int  # features tracked from the previous frame
    num_inliers: int  # PnP inliers (0 when not tracked)
    feature_pixels: np.ndarray  # (N, 2) distorted pixels in the left image
    feature_ages: np.ndarray  # (N,) frames each feature has been tracked
    latency_ms: float  # front end, frame in to pose out (the keyframe work after it not included)
    image_left: np.ndarray | None = None  # for the viewer only (None when not logged)
    reason: str = ""  # why tracking was lost / what happened, for the log
    cpu_ms: float = 0.0  # front-end thread CPU time of this frame (latency_ms minus waiting)
    runqueue_ms: float = -1.0  # of the waiting, runnable without a CPU (-1: OS does not say)
    in_backend_world: bool = False  # False: the VO frame, before the back end's initialisation
    map_from_body: np.ndarray | None = None  # (4, 4), None when not tracked
    map_generation: int = 0  # of the correction applied (0: none yet)
    map_jump_m: float = 0.0
    map_jump_deg: float = 0.0
    anchor_keyframe_id: int = -1
    """While tracked against old landmarks found again in the map: the keyframe most of them
    were born at (-1: none)."""
    feature_reobserved: np.ndarray | None = None  # (N,) bool over feature_pixels: found again
    time_offset_ns: int = 0  # its frame's camera-IMU offset: t_ns minus this is the camera's stamp


@dataclass(frozen=True)
class EndOfStream:
    """Sentinel passed down a stage's queue when its input is exhausted."""

    t_ns: int = 0
    interrupted: bool = False  # the run was stopped (Ctrl-C, SIGTERM): skip optional end work
    run_end_began_s: float | None = None
    """``time.perf_counter()`` when the run's end began (the front end answered its last
    frame); end-of-run time budgets count from it. On Linux that clock is CLOCK_MONOTONIC, the
    same in every process of the machine, so a worker process can compare it with its own."""


@dataclass(frozen=True, eq=False)
class ImuBatch:
    """Consecutive IMU samples handed on together: the player sends the samples between two
    frames as one message (one queue hand-off and thread wake-up per frame, not per sample), and
    the back end forwards them to its worker process in larger batches (fewer pickles)."""

    t_ns: np.ndarray  # (N,) int64
    gyro_rad_s: np.ndarray  # (N, 3)
    accel_m_s2: np.ndarray  # (N, 3)

    @staticmethod
    def from_samples(samples: Sequence[ImuSample]) -> ImuBatch:
        return ImuBatch(
            np.array([s.t_ns for s in samples], dtype=np.int64),
            np.array([s.gyro_rad_s for s in samples], dtype=float).reshape(-1, 3),
            np.array([s.accel_m_s2 for s in samples], dtype=float).reshape(-1, 3),
        )

    @staticmethod
    def concatenate(batches: Sequence[ImuBatch]) -> ImuBatch:
        return ImuBatch(
            np.concatenate([b.t_ns for b in batches]),
            np.concatenate([b.gyro_rad_s for b in batches]),
            np.concatenate([b.accel_m_s2 for b in batches]),
        )

    def __len__(self) -> int:
        return len(self.t_ns)

    def samples(self) -> list[ImuSample]:
        """The batch as :class:`ImuSample` messages, in order."""
        return [
            ImuSample(int(t), self.gyro_rad_s[i], self.accel_m_s2[i])
            for i, t in enumerate(self.t_ns.tolist())
        ]


@dataclass(frozen=True, eq=False)
class KeyframeInertial:
    """A keyframe's inertial state as the back end last estimated it, and the IMU readings
    from the keyframe before it: the global adjustment's IMU factors (``slam.loop.global_ba``,
    option ``loop.global_ba_imu``).

    The readings are as read (no IMU intrinsics applied), as the integration pieces between
    the two keyframe times (``slam.backend.imu.integration_pieces``: each piece's duration and
    mean readings). Velocity and biases are in the back end's (odometry) world."""

    keyframe_id: int
    t_ns: int
    velocity_world_m_s: np.ndarray  # (3,)
    bias_gyro_rad_s: np.ndarray  # (3,)
    bias_accel_m_s2: np.ndarray  # (3,)
    previous_keyframe_id: int  # -1: not joined to the keyframe before it by IMU readings
    piece_dt_s: np.ndarray  # (P,)
    piece_gyro_rad_s: np.ndarray  # (P, 3)
    piece_accel_m_s2: np.ndarray  # (P, 3)

    def with_state(
        self,
        velocity_world_m_s: np.ndarray,
        bias_gyro_rad_s: np.ndarray,
        bias_accel_m_s2: np.ndarray,
    ) -> KeyframeInertial:
        """The same readings with a newer estimate of the state."""
        return KeyframeInertial(
            self.keyframe_id,
            self.t_ns,
            np.asarray(velocity_world_m_s, dtype=float),
            np.asarray(bias_gyro_rad_s, dtype=float),
            np.asarray(bias_accel_m_s2, dtype=float),
            self.previous_keyframe_id,
            self.piece_dt_s,
            self.piece_gyro_rad_s,
            self.piece_accel_m_s2,
        )


@dataclass(frozen=True, eq=False)
class BackendOutput:
    """What the back end returns per keyframe: the new estimate and what it cost."""

    estimate: Estimate | None
    keyframe_id: int
    update_ms: float  # wall time of add_keyframe()
    events: tuple[str, ...] = ()  # initialised, resets, IMU warnings since the last output
    mono_scale: float = 0.0
    """Monocular: the start's scale (metres per VO unit) the alignment tried at this
    keyframe, accepted or not; 0 when none was tried."""
    inertial: tuple[KeyframeInertial, ...] = ()
    """Keyframe states the smoother let go with this update (and at the end, those left in
    its window), for the global adjustment's IMU factors (``loop.global_ba_imu``; else
    empty)."""


@dataclass(frozen=True, eq=False)
class LoopCorrection:
    """A loop closure's drift correction, published after each pose-graph optimisation.

    The front and back ends keep running in their odometry world; ``map_from_odom[segment]``
    (4x4) maps a segment's odometry poses into the loop-corrected map (apply it to poses newer
    than the segment's last corrected keyframe). ``corrected_keyframe_poses`` maps keyframe id
    -> map_from_body for every keyframe the loop closer holds.
    """

    t_ns: int  # time of the newest keyframe when the correction was made
    loop_id: int  # the newest loop in the optimisation (-1: none survived)
    query_keyframe_id: int
    match_keyframe_id: int
    inliers: int
    map_generation: int  # increments with every correction
    map_from_odom: dict[int, np.ndarray]
    corrected_keyframe_poses: dict[int, np.ndarray]


@dataclass(frozen=True, eq=False)
class MapperReport:
    """What the dense mapper did with one keyframe (and how far behind it is)."""

    t_ns: int
    skipped: bool  # not fused: the camera had not moved since the last fused keyframe
    depth_ms: float
    fusion_ms: float
    blocks: int  # allocated TSDF voxel blocks
    reintegrated: int = 0  # keyframes re-integrated at loop-corrected poses after this one
    cpu_ms: float = 0.0  # CPU time of the mapper's process (all threads) for all of it


@dataclass(frozen=True, eq=False)
class MeshSnapshot:
    """The current dense mesh (world frame, metres)."""

    t_ns: int
    vertices_m: np.ndarray  # (N, 3) float32
    faces: np.ndarray  # (M, 3) int32
    normals: np.ndarray  # (N, 3) float32
    colors_rgb: np.ndarray | None  # (N, 3) uint8


# -- the worker-process protocol (slam.runtime.worker) --------------------------------------
@dataclass(frozen=True)
class WorkerReady:
    """A worker process has started and can take input."""

    pid: int


@dataclass(frozen=True)
class WorkerFailed:
    """A worker process's stage failed; the worker ends after sending this."""

    error: str  # "ExceptionType: message"
    trace: str  # the worker's traceback


@dataclass(frozen=True, eq=False)
class WorkerFinal:
    """A worker's last message, after :class:`EndOfStream`: what the stage returns at the end."""

    payload: Any


@dataclass(frozen=True, eq=False)
class WorkerFallback:
    """A final payload without the optional end work that follows it (the loop closer's global
    adjustment), sent before that work starts: the stage ends with it, and the worker is
    stopped, if the :class:`WorkerFinal` has not come by ``use_after_s`` (``time.perf_counter``,
    CLOCK_MONOTONIC on Linux: the same clock in every process)."""

    payload: Any
    use_after_s: float


# -- stage payloads --------------------------------------------------------------------------
@dataclass(frozen=True, eq=False)
class FrontendCorrection:
    """The front end moved its world (the back end's estimate re-anchored it): every pose it
    reported before ``t_ns`` is now ``new_from_old @ pose`` in its belief. ``reframe``: the
    first one, the change from the VO frame into the back end's gravity-aligned world."""

    t_ns: int
    new_from_old: np.ndarray  # (4, 4)
    reframe: bool


@dataclass(frozen=True, eq=False)
class LoopInput:
    """A keyframe for the loop closer, with its odometry pose and its neighbours' newer ones."""

    keyframe: Keyframe  # without the right image (not needed there)
    world_from_body_odom: np.ndarray  # (4, 4)
    refreshed: dict[int, np.ndarray]  # keyframe id -> newer odometry world_from_body


@dataclass(frozen=True, eq=False)
class LoopEnd:
    """Sent to the loop closer after its last keyframe, before its final adjustment."""

    unsmoothed_ids: frozenset[int]  # before the back end's initialisation: left out of it
    refreshed: dict[int, np.ndarray]  # keyframe id -> last odometry world_from_body
    inertial: dict[int, KeyframeInertial] = field(default_factory=dict)
    """Keyframe id -> the back end's final inertial state and IMU readings (the global
    adjustment's IMU factors, ``loop.global_ba_imu``; else empty)."""


@dataclass(frozen=True, eq=False)
class LoopOutput:
    """The loop closer's answer to one :class:`LoopInput`."""

    description: KeyframeDescription  # for the relocaliser's mirror of the keyframe store
    world_from_body_odom: np.ndarray  # (4, 4)
    status: str  # "", or the loop event's status ("accepted", "rejected", "pending")
    reason: str
    correction: LoopCorrection | None


@dataclass(frozen=True, eq=False)
class LoopFinal:
    """The loop closer's state at the end of the run (after the global adjustment)."""

    stats: dict[str, Any]  # the stats.json ``loop_closure`` section
    keyframe_map_from_odom: dict[int, np.ndarray]
    corrected_poses: dict[int, np.ndarray]  # keyframe id -> map_from_body


@dataclass(frozen=True)
class BackendFlush:
    """The end of the back end's input: keyframes it still holds (waiting for the time offset)
    are fused now."""


@dataclass(frozen=True)
class BackendFinal:
    """The back end's counters at the end of the run (stats.json ``backend``)."""

    stats: dict[str, Any]


@dataclass(frozen=True, eq=False)
class MapKeyframe:
    """A keyframe for the dense mapper: its images and camera pose at creation."""

    t_ns: int
    image_left: np.ndarray
    image_right: np.ndarray | None
    world_from_cam0: np.ndarray  # (4, 4)
    landmark_depth_range_m: tuple[float, float] | None = None  # its tracked landmarks' depths


@dataclass(frozen=True, eq=False)
class MapPoseUpdate:
    """Loop-corrected poses of keyframes the mapper holds, during the run (it re-integrates the
    moved ones a few at a time, between keyframes)."""

    world_from_cam0_by_t: dict[int, np.ndarray]  # keyframe t_ns -> corrected world_from_cam0


@dataclass(frozen=True, eq=False)
class MapFinish:
    """Re-integrate keyframes at their final poses, then extract (and write) the mesh."""

    world_from_cam0_by_t: dict[int, np.ndarray]  # keyframe t_ns -> final world_from_cam0
    mesh_path: str | None


@dataclass
class MapperSummary:
    """What the mapper's final step did (stats.json ``mapping``)."""

    fused: int = 0
    skipped_static: int = 0
    reintegrated: int = 0
    vertices: int = 0
    faces: int = 0
    mesh_path: str | None = None
    final_ms: float = 0.0
    error: str | None = None
    depth_ms: list[float] = field(default_factory=list)
    fusion_ms: list[float] = field(default_factory=list)


@dataclass(frozen=True, eq=False)
class ReaderBundle:
    """One frame and the IMU samples before it, from the reader process (or, with ``t_ns``
    None, only the samples after the last frame). The images travel in a shared-memory slot
    (``slot`` >= 0, ``shapes`` left[, right]) or inline."""

    imu: ImuBatch
    t_ns: int | None = None
    index: int = -1
    slot: int = -1  # -1: the images are inline
    shapes: tuple[tuple[int, ...], ...] = ()
    inline: tuple[np.ndarray | None, ...] = ()
    exposure_ns: int = 0  # the frame's (``StereoFrame.exposure_ns``)


@dataclass(frozen=True)
class ReaderEnd:
    """The reader process reached the end of the sequence."""

    warnings: tuple[str, ...]


# -- `slam batch` (tools/batch): a run sent to an engine's worker, and what comes back --------
@dataclass(frozen=True)
class BatchTask:
    """One `slam run` of a batch, as an engine's worker (a local thread, a Ray task) gets it.

    Everything the worker needs travels here: the configuration as YAML text (the worker may be
    on another machine, without the batch's folder), the sequence path as the worker sees it.
    """

    run_id: str  # "sequence/configuration/repN": also the run's folder under OUT/runs
    sequence: str  # the sequence's name in tables
    sequence_path: str  # where the worker reads it
    config: str  # the configuration's name in tables
    config_arg: str | None  # a preset name for `slam run --config`, or None
    config_yaml: str | None  # YAML text passed as a file to `--config` (overrides), or None
    repeat: int  # 1..N
    run_args: tuple[str, ...]  # `--speed max`, `--sequential`, extra `slam run` arguments
    timeout_s: float | None = None  # a run still going after this long is stopped and failed
    fingerprint: str = ""  # of what makes the run's result (a finished run is reused if equal)


@dataclass(frozen=True, eq=False)
class BatchOutcome:
    """A finished (or failed) batch run: its output files and its measurements."""

    run_id: str
    ok: bool
    error: str | None  # one line, when not ok
    files: dict[str, bytes]  # the run's folder, relative path -> content
    metrics: dict[str, Any]  # accuracy against ground truth and the run's stats (summarised)
    process_wall_s: float  # the `slam run` process, start to exit
    host: str  # the machine that ran it
    stopped: bool = False  # ended by the batch being stopped: not a result, run again later

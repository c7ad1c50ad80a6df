"""Every object that crosses a thread or process boundary.

Rules: frozen dataclasses, an integer ``t_ns`` (nanoseconds, sensor clock), SI units in the field
names, picklable. Arrays are never mutated after construction.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True, eq=False)
class ImuSample:
    """One IMU reading in the IMU (= body) frame."""

    t_ns: int
    gyro_rad_s: np.ndarray  # (3,) angular velocity, rad/s
    accel_m_s2: np.ndarray  # (3,) specific force, m/s^2 (gravity included, +9.81 up when still)


@dataclass(frozen=True, eq=False)
class StereoFrame:
    """A (possibly mono) camera frame, images as 8-bit grey, time in the IMU clock."""

    t_ns: int
    left: np.ndarray  # (H, W) uint8, cam0
    right: np.ndarray | None  # (H, W) uint8, cam1, or None for mono
    index: int = -1  # frame number within the sequence, -1 when unknown


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
    gap instead of inventing a pose.
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
    latency_ms: float  # front-end processing time of this frame
    image_left: np.ndarray | None = None  # for the viewer only (None when not logged)
    reason: str = ""  # why tracking was lost / what happened, for the log
    cpu_ms: float = 0.0  # front-end thread CPU time of this frame (latency_ms minus waiting)
    runqueue_ms: float = -1.0  # of the waiting, runnable without a CPU (-1: OS does not say)


@dataclass(frozen=True)
class EndOfStream:
    """Sentinel passed down a stage's queue when its input is exhausted."""

    t_ns: int = 0


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
class BackendOutput:
    """What the back end returns per keyframe: the new estimate and what it cost."""

    estimate: Estimate | None
    keyframe_id: int
    update_ms: float  # wall time of add_keyframe()
    events: tuple[str, ...] = ()  # initialised, resets, IMU warnings since the last output


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


@dataclass(frozen=True, eq=False)
class MeshSnapshot:
    """The current dense mesh (world frame, metres)."""

    t_ns: int
    vertices_m: np.ndarray  # (N, 3) float32
    faces: np.ndarray  # (M, 3) int32
    normals: np.ndarray  # (N, 3) float32
    colors_rgb: np.ndarray | None  # (N, 3) uint8

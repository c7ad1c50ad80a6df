"""A :class:`Sequence` held in memory: for tests, converters and generators.

``InMemorySequence`` takes its frames as arrays. ``random_sequence`` builds a small one with
textured random images, a constant-rate IMU stream and a smooth ground-truth trajectory: handy
for I/O tests that need any valid sequence, not a physically consistent one.
"""

from __future__ import annotations

from collections.abc import Sequence as SequenceOf

import numpy as np

from datasets.rigs import small_rig_calibration
from datasets.sequence import ImuArrays, Sequence
from slam.core.calibration import Calibration
from slam.core.geometry import matrix_to_quat_wxyz
from slam.core.messages import StereoFrame
from slam.core.trajectory import Trajectory


class InMemorySequence(Sequence):
    """Frames, IMU and ground truth given as arrays (frame times increasing, IMU clock)."""

    def __init__(
        self,
        name: str,
        calibration: Calibration,
        frame_t_ns: np.ndarray,
        left: SequenceOf[np.ndarray],
        right: SequenceOf[np.ndarray] | None = None,
        imu: ImuArrays | None = None,
        ground_truth: Trajectory | None = None,
    ) -> None:
        super().__init__(name=name, calibration=calibration, ground_truth=ground_truth)
        self._t_ns = np.asarray(frame_t_ns, dtype=np.int64)
        if len(left) != len(self._t_ns) or (right is not None and len(right) != len(left)):
            raise ValueError("frame times, left and right images must have the same length")
        if len(self._t_ns) > 1 and np.any(np.diff(self._t_ns) <= 0):
            raise ValueError("frame times must be strictly increasing")
        self._left = list(left)
        self._right = list(right) if right is not None else None
        self._imu = imu or ImuArrays(np.zeros(0, np.int64), np.zeros((0, 3)), np.zeros((0, 3)))

    def frame_times_ns(self) -> np.ndarray:
        return self._t_ns

    def imu(self) -> ImuArrays:
        return self._imu

    def frame(self, index: int) -> StereoFrame:
        right = self._right[index] if self._right is not None else None
        return StereoFrame(int(self._t_ns[index]), self._left[index], right, index)


def textured_image(rng: np.random.Generator, width: int, height: int) -> np.ndarray:
    """Blob-textured uint8 image with fine noise (compresses like a real camera image)."""
    import cv2

    coarse = rng.integers(0, 256, (height // 16 + 1, width // 16 + 1), dtype=np.uint8)
    img = cv2.resize(coarse, (width, height), interpolation=cv2.INTER_CUBIC).astype(np.int16)
    img += rng.integers(-6, 7, (height, width), dtype=np.int16)
    return np.clip(img, 0, 255).astype(np.uint8)


def random_sequence(
    *,
    num_frames: int = 10,
    frame_rate_hz: float = 20.0,
    imu_rate_hz: float = 200.0,
    width: int = 64,
    height: int = 48,
    stereo: bool = True,
    start_ns: int = 1_700_000_000_000_000_000,
    time_offset_ns: int = 0,
    seed: int = 0,
    name: str = "random",
) -> InMemorySequence:
    """A small sequence of textured random images, random-ish IMU and a circular GT path."""
    rng = np.random.default_rng(seed)
    frame_dt = round(1e9 / frame_rate_hz)
    imu_dt = round(1e9 / imu_rate_hz)
    t_frames = start_ns + frame_dt * np.arange(num_frames, dtype=np.int64)
    duration = frame_dt * max(num_frames - 1, 0)
    t_imu = start_ns + imu_dt * np.arange(duration // imu_dt + 1, dtype=np.int64)
    imu = ImuArrays(
        t_imu,
        rng.normal(0.0, 0.1, (len(t_imu), 3)),
        rng.normal(0.0, 0.1, (len(t_imu), 3)) + np.array([0.0, 0.0, 9.81]),
    )
    left = [textured_image(rng, width, height) for _ in range(num_frames)]
    right = [textured_image(rng, width, height) for _ in range(num_frames)] if stereo else None
    t_gt = t_imu[::2]
    phase = (t_gt - start_ns) * 1e-9
    pos = np.stack([np.cos(phase), np.sin(phase), 0.1 * phase], axis=1)
    yaw = phase + np.pi / 2
    rot = np.zeros((len(t_gt), 3, 3))
    rot[:, 0, 0], rot[:, 0, 1] = np.cos(yaw), -np.sin(yaw)
    rot[:, 1, 0], rot[:, 1, 1] = np.sin(yaw), np.cos(yaw)
    rot[:, 2, 2] = 1.0
    gt = Trajectory(t_gt, pos, matrix_to_quat_wxyz(rot))
    calib = small_rig_calibration(width, height, stereo, time_offset_ns)
    return InMemorySequence(name, calib, t_frames, left, right, imu, gt)

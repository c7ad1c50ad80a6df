"""One reading interface over every source of camera + IMU data.

A :class:`Sequence` gives the calibration, time-ordered sensor messages (``ImuSample`` and
``StereoFrame``, integer ``t_ns`` in the IMU clock), optional ground truth (world_from_body) and
summary counts. Concrete sources (our MCAP, plain ROS 2 bags, EuRoC/TUM-VI folders, the synthetic
generator) subclass it; :func:`datasets.open.open_sequence` picks the right one for a path.

Data-quality problems found while reading (sorted or dropped timestamps, IMU gaps, truncation)
are appended to ``warnings`` and logged; they never pass silently.
"""

from __future__ import annotations

import logging
from abc import ABC, abstractmethod
from collections.abc import Iterator
from dataclasses import dataclass, field

import numpy as np

from slam.core.calibration import Calibration
from slam.core.messages import ImuSample, StereoFrame, mid_exposure_ns
from slam.core.trajectory import Trajectory

log = logging.getLogger(__name__)


@dataclass(frozen=True, eq=False)
class ImuArrays:
    """The whole IMU stream as arrays: t_ns (N,) int64, gyro_rad_s (N, 3), accel_m_s2 (N, 3)."""

    t_ns: np.ndarray
    gyro_rad_s: np.ndarray
    accel_m_s2: np.ndarray

    def __len__(self) -> int:
        return len(self.t_ns)


@dataclass
class Sequence(ABC):
    """Base class of every sequence source."""

    name: str
    calibration: Calibration
    ground_truth: Trajectory | None = None
    warnings: list[str] = field(default_factory=list)

    # --- what subclasses provide -------------------------------------------------------------
    @abstractmethod
    def frame_times_ns(self) -> np.ndarray:
        """Timestamps (int64 ns, IMU clock) of every camera frame, increasing."""

    @abstractmethod
    def imu(self) -> ImuArrays:
        """The whole IMU stream (may be empty), increasing time."""

    @abstractmethod
    def frame(self, index: int) -> StereoFrame:
        """Random access to one camera frame (decoded)."""

    def exposures_ns(self) -> np.ndarray | None:
        """Each frame's exposure duration (int64 ns, one per ``frame_times_ns``; frames carry
        theirs as ``StereoFrame.exposure_ns``), or None: the source does not record it."""
        return None

    # --- derived -----------------------------------------------------------------------------
    def image_times_ns(self) -> np.ndarray:
        """The time each frame's image shows (:func:`slam.core.messages.mid_exposure_ns`: the
        middle of its exposure where the source records it, else its stamp), int64 ns."""
        times = self.frame_times_ns()
        exposures = self.exposures_ns()
        return times if exposures is None else mid_exposure_ns(times, exposures)

    def iter_frames(self) -> Iterator[StereoFrame]:
        """Frames in time order. Subclasses may override with a faster streaming read."""
        for i in range(len(self.frame_times_ns())):
            yield self.frame(i)

    def messages(self) -> Iterator[ImuSample | StereoFrame]:
        """IMU samples and frames merged in time order (an IMU sample before a frame at equal t)."""
        imu = self.imu()
        j = 0
        n_imu = len(imu)
        for frame in self.iter_frames():
            while j < n_imu and imu.t_ns[j] <= frame.t_ns:
                yield ImuSample(int(imu.t_ns[j]), imu.gyro_rad_s[j], imu.accel_m_s2[j])
                j += 1
            yield frame
        while j < n_imu:
            yield ImuSample(int(imu.t_ns[j]), imu.gyro_rad_s[j], imu.accel_m_s2[j])
            j += 1

    @property
    def num_frames(self) -> int:
        return len(self.frame_times_ns())

    @property
    def num_imu(self) -> int:
        return len(self.imu())

    @property
    def has_imu(self) -> bool:
        """An IMU in the calibration and samples of it in the data."""
        return self.calibration.imu is not None and self.num_imu > 0

    def start_ns(self) -> int:
        starts = [int(a[0]) for a in (self.frame_times_ns(), self.imu().t_ns) if len(a)]
        return min(starts) if starts else 0

    def end_ns(self) -> int:
        ends = [int(a[-1]) for a in (self.frame_times_ns(), self.imu().t_ns) if len(a)]
        return max(ends) if ends else 0

    @property
    def duration_ns(self) -> int:
        return self.end_ns() - self.start_ns()

    def warn(self, message: str) -> None:
        """Record and log a data-quality warning."""
        self.warnings.append(message)
        log.warning("%s: %s", self.name, message)

"""A stereo sequence read as monocular: cam0 and the IMU (the ``euroc-mono-imu`` preset on a
stereo source). The right images are dropped as frames are read, so they are never decoded
into the pipeline's shared memory nor reach a stage."""

from __future__ import annotations

import dataclasses
from collections.abc import Iterator
from dataclasses import dataclass

import numpy as np

from datasets.sequence import ImuArrays, Sequence
from slam.core.messages import ImuSample, StereoFrame


@dataclass
class Cam0Only(Sequence):
    """``source`` without cam1 (calibration and frames)."""

    source: Sequence | None = None

    @staticmethod
    def of(source: Sequence) -> Sequence:
        """``source`` itself when it is mono already, else its cam0-only view."""
        if not source.calibration.is_stereo:
            return source
        calib = dataclasses.replace(source.calibration, cameras=source.calibration.cameras[:1])
        return Cam0Only(
            name=source.name,
            calibration=calib,
            ground_truth=source.ground_truth,
            warnings=source.warnings,
            source=source,
        )

    def _src(self) -> Sequence:
        assert self.source is not None
        return self.source

    def frame_times_ns(self) -> np.ndarray:
        return self._src().frame_times_ns()

    def imu(self) -> ImuArrays:
        return self._src().imu()

    def exposures_ns(self) -> np.ndarray | None:
        return self._src().exposures_ns()

    def frame(self, index: int) -> StereoFrame:
        return dataclasses.replace(self._src().frame(index), right=None)

    def iter_frames(self) -> Iterator[StereoFrame]:
        for f in self._src().iter_frames():
            yield dataclasses.replace(f, right=None)

    def messages(self) -> Iterator[ImuSample | StereoFrame]:
        for m in self._src().messages():
            yield dataclasses.replace(m, right=None) if isinstance(m, StereoFrame) else m

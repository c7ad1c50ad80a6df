"""Every object that crosses a thread or process boundary.

Rules: frozen dataclasses, an integer ``t_ns`` (nanoseconds, sensor clock), SI units in the field
names, picklable. Arrays are never mutated after construction.
"""

from __future__ import annotations

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

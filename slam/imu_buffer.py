"""A thread-safe, time-bounded buffer of IMU samples and gyro integration between two times."""

from __future__ import annotations

import bisect
import threading

import numpy as np

from slam.geometry import so3_exp
from slam.messages import ImuSample


class ImuBuffer:
    """Append-only (in time order) IMU store that forgets samples older than ``keep_ns``.

    The player appends; the front end reads windows (binary search on a list of times: the
    front end calls this twice per frame, so it must not copy the whole buffer). Reads copy out
    under the lock, so no caller ever sees a half-written sample.
    """

    def __init__(self, keep_ns: int = 5_000_000_000):
        self._lock = threading.Lock()
        self._t: list[int] = []
        self._samples: list[ImuSample] = []
        self._keep_ns = keep_ns

    def append(self, sample: ImuSample) -> None:
        if not (np.isfinite(sample.gyro_rad_s).all() and np.isfinite(sample.accel_m_s2).all()):
            return  # the back end counts and reports bad samples; the front end just skips them
        with self._lock:
            if self._t and sample.t_ns <= self._t[-1]:
                return
            self._t.append(sample.t_ns)
            self._samples.append(sample)
            if sample.t_ns - self._t[0] > 2 * self._keep_ns:  # trim in bulk: amortised O(1)
                cut = bisect.bisect_left(self._t, sample.t_ns - self._keep_ns)
                del self._t[:cut]
                del self._samples[:cut]

    def window(self, t0_ns: int, t1_ns: int) -> list[ImuSample]:
        """Samples with t0 - one sample <= t <= t1 + one sample (enough to cover [t0, t1])."""
        with self._lock:
            if not self._t:
                return []
            i0 = max(bisect.bisect_right(self._t, t0_ns) - 1, 0)
            i1 = min(bisect.bisect_left(self._t, t1_ns) + 1, len(self._t))
            return self._samples[i0:i1]


def integrate_gyro(
    samples: list[ImuSample], t0_ns: int, t1_ns: int, bias_gyro_rad_s: np.ndarray | None = None
) -> np.ndarray | None:
    """Rotation body(t0)_from_body(t1) from gyro samples (piecewise constant), or None if the
    samples do not cover [t0, t1]."""
    if t1_ns <= t0_ns:
        return np.eye(3)
    if not samples or samples[0].t_ns > t0_ns + 10_000_000 or samples[-1].t_ns < t1_ns - 10_000_000:
        return None
    bias = np.zeros(3) if bias_gyro_rad_s is None else bias_gyro_rad_s
    rot = np.eye(3)
    for k, s in enumerate(samples):
        start = max(s.t_ns, t0_ns)
        end = samples[k + 1].t_ns if k + 1 < len(samples) else t1_ns
        end = min(end, t1_ns)
        if end <= start:
            continue
        dt = (end - start) * 1e-9
        rot = rot @ so3_exp((s.gyro_rad_s - bias) * dt)
    return rot


def propagate_pose(
    samples: list[ImuSample],
    t0_ns: int,
    t1_ns: int,
    world_from_body: np.ndarray,
    velocity_world_m_s: np.ndarray,
    bias_gyro_rad_s: np.ndarray,
    bias_accel_m_s2: np.ndarray,
    gravity_m_s2: float = 9.81,
) -> tuple[np.ndarray, np.ndarray] | None:
    """Dead-reckon (world_from_body, velocity) from t0 to t1 with the IMU (world z up).

    Piecewise-constant samples, the same model as the preintegration. Returns None when the
    samples do not cover [t0, t1]. Used for the front end's pose prior, not for estimation.
    """
    if t1_ns <= t0_ns:
        return world_from_body.copy(), velocity_world_m_s.copy()
    if not samples or samples[0].t_ns > t0_ns + 10_000_000 or samples[-1].t_ns < t1_ns - 10_000_000:
        return None
    g = np.array([0.0, 0.0, -gravity_m_s2])
    rot = world_from_body[:3, :3].copy()
    pos = world_from_body[:3, 3].copy()
    vel = np.asarray(velocity_world_m_s, dtype=float).copy()
    for k, s in enumerate(samples):
        start = max(s.t_ns, t0_ns)
        end = min(samples[k + 1].t_ns if k + 1 < len(samples) else t1_ns, t1_ns)
        if end <= start:
            continue
        dt = (end - start) * 1e-9
        acc_world = rot @ (s.accel_m_s2 - bias_accel_m_s2) + g
        pos = pos + vel * dt + 0.5 * acc_world * dt * dt
        vel = vel + acc_world * dt
        rot = rot @ so3_exp((s.gyro_rad_s - bias_gyro_rad_s) * dt)
    out = np.eye(4)
    out[:3, :3] = rot
    out[:3, 3] = pos
    return out, vel

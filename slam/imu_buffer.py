"""A thread-safe, time-bounded buffer of IMU samples and gyro integration between two times."""

from __future__ import annotations

import bisect
import math
import threading
from collections.abc import Iterable

import numpy as np

from slam.geometry import so3_exp_batch
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
        self.extend((sample,))

    def extend(self, samples: Iterable[ImuSample]) -> None:
        """Append samples in time order (one lock for all of them)."""
        with self._lock:
            for sample in samples:
                if not math.isfinite(float(np.sum(sample.gyro_rad_s) + np.sum(sample.accel_m_s2))):
                    continue  # the back end counts and reports bad samples; the front end skips
                if self._t and sample.t_ns <= self._t[-1]:
                    continue
                self._t.append(sample.t_ns)
                self._samples.append(sample)
            if self._t and self._t[-1] - self._t[0] > 2 * self._keep_ns:  # trim in bulk
                cut = bisect.bisect_left(self._t, self._t[-1] - self._keep_ns)
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


def _intervals(
    samples: list[ImuSample], t0_ns: int, t1_ns: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """The piecewise-constant model over [t0, t1]: (dt_s (M,), gyro (M, 3), accel (M, 3)) of
    the samples that cover a non-empty part of it, or None if the samples do not cover it."""
    if not samples or samples[0].t_ns > t0_ns + 10_000_000 or samples[-1].t_ns < t1_ns - 10_000_000:
        return None
    t = np.fromiter((s.t_ns for s in samples), dtype=np.int64, count=len(samples))
    start = np.maximum(t, t0_ns)
    end = np.minimum(np.append(t[1:], t1_ns), t1_ns)
    use = np.flatnonzero(end > start)
    dt_s = (end[use] - start[use]) * 1e-9
    gyro = np.array([samples[i].gyro_rad_s for i in use.tolist()], dtype=float).reshape(-1, 3)
    accel = np.array([samples[i].accel_m_s2 for i in use.tolist()], dtype=float).reshape(-1, 3)
    return dt_s, gyro, accel


def integrate_gyro(
    samples: list[ImuSample], t0_ns: int, t1_ns: int, bias_gyro_rad_s: np.ndarray | None = None
) -> np.ndarray | None:
    """Rotation body(t0)_from_body(t1) from gyro samples (piecewise constant), or None if the
    samples do not cover [t0, t1]."""
    if t1_ns <= t0_ns:
        return np.eye(3)
    model = _intervals(samples, t0_ns, t1_ns)
    if model is None:
        return None
    dt_s, gyro, _ = model
    bias = np.zeros(3) if bias_gyro_rad_s is None else bias_gyro_rad_s
    rot = np.eye(3)
    for step in so3_exp_batch((gyro - bias) * dt_s[:, None]):
        rot = rot @ step
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
    Vectorised over the samples except for the chain of rotations.
    """
    if t1_ns <= t0_ns:
        return world_from_body.copy(), velocity_world_m_s.copy()
    model = _intervals(samples, t0_ns, t1_ns)
    if model is None:
        return None
    dt_s, gyro, accel = model
    steps = so3_exp_batch((gyro - bias_gyro_rad_s) * dt_s[:, None])
    rots = np.empty((len(dt_s) + 1, 3, 3))  # world_from_body at the start of each interval
    rots[0] = world_from_body[:3, :3]
    for k, step in enumerate(steps):
        rots[k + 1] = rots[k] @ step
    g = np.array([0.0, 0.0, -gravity_m_s2])
    acc_world = np.einsum("nij,nj->ni", rots[:-1], accel - bias_accel_m_s2) + g
    dv = acc_world * dt_s[:, None]
    vel0 = np.asarray(velocity_world_m_s, dtype=float)
    vel_before = vel0 + np.vstack([np.zeros(3), np.cumsum(dv, axis=0)[:-1]])
    dp = vel_before * dt_s[:, None] + 0.5 * acc_world * (dt_s**2)[:, None]
    out = np.eye(4)
    out[:3, :3] = rots[-1]
    out[:3, 3] = world_from_body[:3, 3] + dp.sum(axis=0)
    return out, vel0 + dv.sum(axis=0)

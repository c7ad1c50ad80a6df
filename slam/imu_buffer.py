"""The IMU sample store of the front and back ends, and the front end's IMU integration.

``ImuBuffer`` is the one IMU store: the player fills the front end's (gyro prediction and pose
prior), the back end fills its own (preintegration, initialisation). Both reject non-finite
and out-of-order samples and count every problem in ``stats``; what differs is configured:

- the front end's (``ImuBuffer()``) forgets samples older than ``keep_ns`` by itself and stays
  quiet (the back end reports the same problems once);
- the back end's (``slam.backend.imu.backend_imu_buffer``) keeps samples until ``trim()``,
  also rejects saturated samples, counts gaps and logs every kind of problem (its ``stats``
  go into stats.json ``backend.imu``).

Every read and write holds a lock (the player appends while the front end reads): ``window``
returns a new list, ``arrays`` cached arrays that are replaced, never modified, when the samples
change.

The store is also where the IMU's intrinsics are applied (``set_intrinsics``: the back end's
online estimate, ``slam.backend.imu_intrinsics``): samples are kept as read, and every reading
(``window``, ``arrays``) is ``matrix @ raw`` per sensor; ``raw_arrays`` gives them as read.
Without intrinsics (or with the identity) the readings are the stored samples themselves.
"""

from __future__ import annotations

import bisect
import logging
import math
import threading
from collections.abc import Iterable
from dataclasses import dataclass, field

import numpy as np

from slam.core.geometry import so3_exp_batch
from slam.core.messages import ImuBatch, ImuIntrinsics, ImuSample

log = logging.getLogger(__name__)


@dataclass
class ImuStats:
    """Counters of IMU data problems (all samples are counted once)."""

    accepted: int = 0
    rejected_nonfinite: int = 0
    rejected_saturated: int = 0
    rejected_out_of_order: int = 0
    gaps_warned: int = 0
    intervals_without_imu: int = 0  # keyframe intervals that got no IMU factor (the back end's)
    messages: list[str] = field(default_factory=list)

    @property
    def rejected(self) -> int:
        return self.rejected_nonfinite + self.rejected_saturated + self.rejected_out_of_order


class ImuBuffer:
    """Time-ordered IMU samples: sanitised on the way in, read as sample windows or arrays.

    ``keep_ns``: samples older than this before the newest are forgotten (in bulk, once the
    buffer spans twice as long); None keeps everything until :meth:`trim`.
    ``max_gyro_rad_s`` / ``max_accel_m_s2``: saturation limits (any axis above them: rejected).
    ``gap_warn_ns``: an interval between accepted samples longer than this is counted as a gap.
    ``log_problems``: log a warning on the first problem of a kind and every 100th after it.
    """

    _WARN_EVERY = 100  # after the first warning of a kind, log every this many occurrences

    def __init__(
        self,
        keep_ns: int | None = 5_000_000_000,
        *,
        max_gyro_rad_s: float = math.inf,
        max_accel_m_s2: float = math.inf,
        gap_warn_ns: float = math.inf,
        log_problems: bool = False,
    ) -> None:
        self.stats = ImuStats()
        self._keep_ns = keep_ns
        self._max_gyro_rad_s = max_gyro_rad_s
        self._max_accel_m_s2 = max_accel_m_s2
        self._check_saturation = math.isfinite(max_gyro_rad_s) or math.isfinite(max_accel_m_s2)
        self._gap_warn_ns = gap_warn_ns
        self._log_problems = log_problems
        self._lock = threading.Lock()
        self._t: list[int] = []
        self._samples: list[ImuSample] = []
        self._cache: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None
        self._raw_cache: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None
        self._intrinsics: ImuIntrinsics | None = None  # None: readings as stored

    def __len__(self) -> int:
        return len(self._t)

    # ------------------------------------------------------------------ writing
    def add(self, sample: ImuSample) -> bool:
        """Append one sample; returns False (and counts it) when it is rejected."""
        with self._lock:
            accepted = self._accept(sample)
            self._forget_old()
        return accepted

    def extend(self, samples: Iterable[ImuSample]) -> int:
        """Append samples in time order (one lock for all of them); returns how many were kept."""
        return self.extend_batch(ImuBatch.from_samples(list(samples)))

    def extend_batch(self, batch: ImuBatch) -> int:
        """:meth:`extend` for a batch, checked with numpy: the same samples kept, the same
        counts and warnings as :meth:`add` one by one. The player hands the front end's buffer
        a batch per frame; sample by sample, the checks were the largest share of the time the
        player's thread held the GIL that the front end's thread waits for (py-spy ``--gil``
        on room-figure8 in real time: 15 % of all GIL-held samples)."""
        t = np.asarray(batch.t_ns, dtype=np.int64).reshape(-1)
        gyro = np.asarray(batch.gyro_rad_s, dtype=float).reshape(-1, 3)
        accel = np.asarray(batch.accel_m_s2, dtype=float).reshape(-1, 3)
        if len(t) == 0:
            return 0
        with self._lock:
            finite = np.isfinite(gyro).all(axis=1) & np.isfinite(accel).all(axis=1)
            saturated = np.zeros(len(t), dtype=bool)
            if self._check_saturation:
                saturated[finite] = (np.abs(accel[finite]).max(axis=1) > self._max_accel_m_s2) | (
                    np.abs(gyro[finite]).max(axis=1) > self._max_gyro_rad_s
                )
            candidates = np.flatnonzero(finite & ~saturated)
            # A sample is late when it is not after every earlier one kept: a late one never
            # raises that bound, so the running maximum over all candidates is it.
            first = self._t[-1] if self._t else np.iinfo(np.int64).min
            bound = np.maximum.accumulate(np.concatenate(([first], t[candidates])))[:-1]
            late = np.zeros(len(t), dtype=bool)
            late[candidates[t[candidates] <= bound]] = True
            kept = candidates[t[candidates] > bound]
            gap_ns = np.zeros(len(t), dtype=np.int64)  # > 0: a gap before sample i
            if len(kept) and math.isfinite(self._gap_warn_ns):
                step_ns = np.diff(np.concatenate(([first], t[kept])))
                if not self._t:
                    step_ns[0] = 0  # the first sample ever has nothing before it
                is_gap = step_ns > self._gap_warn_ns
                gap_ns[kept[is_gap]] = step_ns[is_gap]
            for i in np.flatnonzero(~finite | saturated | late | (gap_ns > 0)).tolist():
                self._count_problem(int(t[i]), finite[i], saturated[i], late[i], int(gap_ns[i]))
            if len(kept):
                self._t.extend(t[kept].tolist())
                self._samples.extend(ImuSample(int(t[i]), gyro[i], accel[i]) for i in kept.tolist())
                self._cache = self._raw_cache = None
                self.stats.accepted += len(kept)
            self._forget_old()
        return len(kept)

    def _count_problem(
        self, t_ns: int, finite: bool, saturated: bool, late: bool, gap_ns: int
    ) -> None:
        """Count and warn about one sample's problem (the first of these that it has), for
        :meth:`_accept` and :meth:`extend_batch` alike."""
        s = self.stats
        if not finite:
            s.rejected_nonfinite += 1
            self._warn("nonfinite", s.rejected_nonfinite, f"non-finite sample at t={t_ns}")
        elif saturated:
            s.rejected_saturated += 1
            self._warn("saturated", s.rejected_saturated, f"saturated sample at t={t_ns}")
        elif late:
            s.rejected_out_of_order += 1
            self._warn("out_of_order", s.rejected_out_of_order, f"non-increasing time t={t_ns}")
        elif gap_ns > 0:
            s.gaps_warned += 1
            self._warn("gap", s.gaps_warned, f"gap of {gap_ns * 1e-9:.3f} s before t={t_ns}")

    def trim(self, before_ns: int) -> None:
        """Drop samples older than ``before_ns`` except the last one before it (for bracketing)."""
        with self._lock:
            k = bisect.bisect_right(self._t, before_ns) - 1
            if k > 0:
                self._drop_first(k)

    def _warn(self, kind: str, count: int, text: str) -> None:
        if self._log_problems and (count == 1 or count % self._WARN_EVERY == 0):
            msg = f"IMU: {text} ({kind} count {count})"
            log.warning(msg)
            if len(self.stats.messages) < 50:
                self.stats.messages.append(msg)

    def _accept(self, sample: ImuSample) -> bool:
        gyro = np.asarray(sample.gyro_rad_s, dtype=float).reshape(3)
        accel = np.asarray(sample.accel_m_s2, dtype=float).reshape(3)
        t_ns = int(sample.t_ns)
        finite = bool(np.all(np.isfinite(gyro)) and np.all(np.isfinite(accel)))
        saturated = (
            finite
            and self._check_saturation
            and bool(
                np.abs(accel).max() > self._max_accel_m_s2
                or np.abs(gyro).max() > self._max_gyro_rad_s
            )
        )
        late = bool(self._t) and t_ns <= self._t[-1]
        step_ns = t_ns - self._t[-1] if self._t else 0
        gap_ns = step_ns if step_ns > self._gap_warn_ns else 0
        if not finite or saturated or late or gap_ns > 0:
            self._count_problem(t_ns, finite, saturated, late, gap_ns)
        if not finite or saturated or late:
            return False
        self._t.append(t_ns)
        self._samples.append(sample)
        self._cache = self._raw_cache = None
        self.stats.accepted += 1
        return True

    def _forget_old(self) -> None:
        if self._keep_ns is not None and self._t and self._t[-1] - self._t[0] > 2 * self._keep_ns:
            self._drop_first(bisect.bisect_left(self._t, self._t[-1] - self._keep_ns))

    def _drop_first(self, count: int) -> None:
        del self._t[:count], self._samples[:count]
        self._cache = self._raw_cache = None

    def set_intrinsics(self, intrinsics: ImuIntrinsics | None) -> None:
        """Read every sample (kept and future) through these correction matrices from now on;
        None or the identity: the samples as read."""
        new = None if intrinsics is None or intrinsics.is_identity else intrinsics
        with self._lock:
            if new is self._intrinsics:
                return
            self._intrinsics = new
            self._cache = None

    # ------------------------------------------------------------------ reading
    def window(self, t0_ns: int, t1_ns: int) -> list[ImuSample]:
        """Samples with t0 - one sample <= t <= t1 + one sample (enough to cover [t0, t1])."""
        with self._lock:
            if not self._t:
                return []
            i0 = max(bisect.bisect_right(self._t, t0_ns) - 1, 0)
            i1 = min(bisect.bisect_left(self._t, t1_ns) + 1, len(self._t))
            samples = self._samples[i0:i1]
            intrinsics = self._intrinsics
        if intrinsics is None or not samples:
            return samples
        gyro = np.array([s.gyro_rad_s for s in samples], dtype=float) @ intrinsics.gyro_matrix.T
        accel = np.array([s.accel_m_s2 for s in samples], dtype=float) @ intrinsics.accel_matrix.T
        return [ImuSample(s.t_ns, g, a) for s, g, a in zip(samples, gyro, accel, strict=True)]

    def arrays(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(t_ns (N,), gyro (N, 3), accel (N, 3)) of the kept samples, read through the
        intrinsics (cached until changed)."""
        with self._lock:
            if self._cache is None:
                t_ns, gyro, accel = self._raw_locked()
                m = self._intrinsics
                if m is not None:
                    gyro, accel = gyro @ m.gyro_matrix.T, accel @ m.accel_matrix.T
                self._cache = (t_ns, gyro, accel)
            return self._cache

    def raw_arrays(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """:meth:`arrays` as read, without the intrinsics."""
        with self._lock:
            return self._raw_locked()

    def _raw_locked(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        if self._raw_cache is None:
            samples = self._samples
            self._raw_cache = (
                np.asarray(self._t, dtype=np.int64),
                np.array([s.gyro_rad_s for s in samples], dtype=float).reshape(-1, 3),
                np.array([s.accel_m_s2 for s in samples], dtype=float).reshape(-1, 3),
            )
        return self._raw_cache

    def arrays_between(self, t0_ns: int, t1_ns: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """:meth:`arrays` of the samples with t0_ns <= t <= t1_ns (copies)."""
        t, g, a = self.arrays()
        m = (t >= t0_ns) & (t <= t1_ns)
        return t[m], g[m], a[m]


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

    Piecewise-constant samples (the back end's preintegration integrates trapezoidal pieces,
    ``slam.backend.imu.integration_pieces``). Returns None when the samples do not cover
    [t0, t1]. Used for the front end's pose prior, not for estimation.
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

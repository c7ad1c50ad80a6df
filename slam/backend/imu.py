"""IMU preintegration helpers and the sanitised IMU buffer of the back end.

Preintegration uses GTSAM's ``PreintegratedCombinedMeasurements`` (navigation frame z up,
gravity ``-g z``). Noise densities are Kalibr's continuous-time ones; GTSAM takes continuous-time
covariances (density^2) and discretises them itself (divides by dt for white noise, multiplies
by dt for bias random walks).

Between two keyframe times the samples are integrated piecewise: the knots are the two keyframe
times and every sample time strictly between them; each piece uses the mean of the
linearly-interpolated readings at its two knots (trapezoidal rule). The boundary intervals are
thus split exactly at the keyframe times.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field

import gtsam
import numpy as np

from slam.backend.config import BackendConfig
from slam.calibration import ImuCalibration
from slam.messages import ImuSample

log = logging.getLogger(__name__)


def preintegration_params(imu: ImuCalibration) -> gtsam.PreintegrationCombinedParams:
    """GTSAM combined-preintegration parameters from Kalibr-style noise densities."""
    params = gtsam.PreintegrationCombinedParams.MakeSharedU(imu.gravity_m_s2)
    eye = np.eye(3)
    params.setGyroscopeCovariance(imu.gyro_noise_density**2 * eye)
    params.setAccelerometerCovariance(imu.accel_noise_density**2 * eye)
    params.setBiasOmegaCovariance(imu.gyro_random_walk**2 * eye)
    params.setBiasAccCovariance(imu.accel_random_walk**2 * eye)
    params.setIntegrationCovariance(1e-8 * eye)
    return params


def make_bias(gyro_rad_s: np.ndarray, accel_m_s2: np.ndarray) -> gtsam.imuBias.ConstantBias:
    """GTSAM bias object (its constructor takes accel first)."""
    return gtsam.imuBias.ConstantBias(
        np.asarray(accel_m_s2, dtype=float), np.asarray(gyro_rad_s, dtype=float)
    )


def integration_pieces(
    t_ns: np.ndarray,
    gyro_rad_s: np.ndarray,
    accel_m_s2: np.ndarray,
    t0_ns: int,
    t1_ns: int,
    max_gap_s: float,
) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """Pieces (dt_s (P,), gyro (P, 3), accel (P, 3)) covering [t0_ns, t1_ns] exactly.

    Returns None when the samples do not cover the interval or an interval between samples
    (including the distance from a keyframe time to the nearest sample outside it) is longer
    than ``max_gap_s``.
    """
    if t1_ns <= t0_ns or len(t_ns) == 0:
        return None
    i_first = int(np.searchsorted(t_ns, t0_ns, side="right")) - 1  # last sample <= t0
    i_last = int(np.searchsorted(t_ns, t1_ns, side="left"))  # first sample >= t1
    lo = max(i_first, 0)
    hi = min(i_last, len(t_ns) - 1)
    bracket = t_ns[lo : hi + 1]
    edges = np.concatenate(([min(t0_ns, bracket[0])], bracket, [max(t1_ns, bracket[-1])]))
    if np.diff(edges).max() * 1e-9 > max_gap_s:
        return None
    inner = (t_ns > t0_ns) & (t_ns < t1_ns)
    knots = np.concatenate(([t0_ns], t_ns[inner], [t1_ns])).astype(np.int64)
    t_rel = (t_ns - t0_ns).astype(np.float64)
    k_rel = (knots - t0_ns).astype(np.float64)
    g = np.stack([np.interp(k_rel, t_rel, gyro_rad_s[:, a]) for a in range(3)], axis=1)
    acc = np.stack([np.interp(k_rel, t_rel, accel_m_s2[:, a]) for a in range(3)], axis=1)
    dt_s = np.diff(knots).astype(np.float64) * 1e-9
    return dt_s, 0.5 * (g[:-1] + g[1:]), 0.5 * (acc[:-1] + acc[1:])


def integrate_pieces(
    pim: gtsam.PreintegratedCombinedMeasurements,
    pieces: tuple[np.ndarray, np.ndarray, np.ndarray],
) -> None:
    """Feed pieces to a preintegrator (about 2 us per piece)."""
    dt_s, gyro, accel = pieces
    for k in range(len(dt_s)):
        if dt_s[k] > 0.0:
            pim.integrateMeasurement(accel[k], gyro[k], float(dt_s[k]))


@dataclass
class ImuStats:
    """Counters of IMU data problems (all samples are counted once)."""

    accepted: int = 0
    rejected_nonfinite: int = 0
    rejected_saturated: int = 0
    rejected_out_of_order: int = 0
    gaps_warned: int = 0
    intervals_without_imu: int = 0  # keyframe intervals that got no IMU factor
    messages: list[str] = field(default_factory=list)

    @property
    def rejected(self) -> int:
        return self.rejected_nonfinite + self.rejected_saturated + self.rejected_out_of_order


class ImuBuffer:
    """Sanitised IMU history: rejects NaN/inf, saturated and out-of-order samples, warns on gaps."""

    _WARN_EVERY = 100  # after the first warning of a kind, log every this many occurrences

    def __init__(self, imu: ImuCalibration, config: BackendConfig) -> None:
        self.imu = imu
        self.config = config
        self.stats = ImuStats()
        self._nominal_dt_ns = int(round(1e9 / imu.rate_hz))
        self._t: list[int] = []
        self._gyro: list[np.ndarray] = []
        self._accel: list[np.ndarray] = []
        self._cache: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None

    def __len__(self) -> int:
        return len(self._t)

    def _warn(self, kind: str, count: int, text: str) -> None:
        if count == 1 or count % self._WARN_EVERY == 0:
            msg = f"IMU: {text} ({kind} count {count})"
            log.warning(msg)
            if len(self.stats.messages) < 50:
                self.stats.messages.append(msg)

    def add(self, sample: ImuSample) -> bool:
        """Append one sample; returns False (and counts/warns) when it is rejected."""
        gyro = np.asarray(sample.gyro_rad_s, dtype=float).reshape(3)
        accel = np.asarray(sample.accel_m_s2, dtype=float).reshape(3)
        s = self.stats
        if not (np.all(np.isfinite(gyro)) and np.all(np.isfinite(accel))):
            s.rejected_nonfinite += 1
            self._warn("nonfinite", s.rejected_nonfinite, f"non-finite sample at t={sample.t_ns}")
            return False
        if (
            np.abs(accel).max() > self.config.max_accel_m_s2
            or np.abs(gyro).max() > self.config.max_gyro_rad_s
        ):
            s.rejected_saturated += 1
            self._warn("saturated", s.rejected_saturated, f"saturated sample at t={sample.t_ns}")
            return False
        if self._t and sample.t_ns <= self._t[-1]:
            s.rejected_out_of_order += 1
            self._warn(
                "out_of_order", s.rejected_out_of_order, f"non-increasing time t={sample.t_ns}"
            )
            return False
        if self._t:
            gap_ns = sample.t_ns - self._t[-1]
            if gap_ns > self.config.imu_gap_warn_factor * self._nominal_dt_ns:
                s.gaps_warned += 1
                self._warn(
                    "gap", s.gaps_warned, f"gap of {gap_ns * 1e-9:.3f} s before t={sample.t_ns}"
                )
        self._t.append(int(sample.t_ns))
        self._gyro.append(gyro)
        self._accel.append(accel)
        self._cache = None
        s.accepted += 1
        return True

    def arrays(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(t_ns (N,), gyro (N, 3), accel (N, 3)) of the accepted samples."""
        if self._cache is None:
            if not self._t:
                self._cache = (np.zeros(0, np.int64), np.zeros((0, 3)), np.zeros((0, 3)))
            else:
                self._cache = (
                    np.asarray(self._t, dtype=np.int64),
                    np.asarray(self._gyro),
                    np.asarray(self._accel),
                )
        return self._cache

    def window(self, t0_ns: int, t1_ns: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Accepted samples with t0_ns <= t <= t1_ns."""
        t, g, a = self.arrays()
        m = (t >= t0_ns) & (t <= t1_ns)
        return t[m], g[m], a[m]

    def pieces(self, t0_ns: int, t1_ns: int) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
        """Integration pieces over [t0_ns, t1_ns], or None when the IMU does not cover it."""
        t, g, a = self.arrays()
        return integration_pieces(t, g, a, t0_ns, t1_ns, self.config.imu_gap_max_s)

    def preintegrate(
        self,
        params: gtsam.PreintegrationCombinedParams,
        bias: gtsam.imuBias.ConstantBias,
        t0_ns: int,
        t1_ns: int,
    ) -> gtsam.PreintegratedCombinedMeasurements | None:
        """Preintegrated measurements between two keyframe times, or None (no IMU factor)."""
        pieces = self.pieces(t0_ns, t1_ns)
        if pieces is None:
            return None
        pim = gtsam.PreintegratedCombinedMeasurements(params, bias)
        integrate_pieces(pim, pieces)
        return pim

    def trim(self, before_ns: int) -> None:
        """Drop samples older than ``before_ns`` except the last one before it (for bracketing)."""
        t, _, _ = self.arrays()
        k = int(np.searchsorted(t, before_ns, side="right")) - 1
        if k > 0:
            del self._t[:k], self._gyro[:k], self._accel[:k]
            self._cache = None


def propagate_state(
    world_from_body: np.ndarray,
    velocity_world_m_s: np.ndarray,
    bias_gyro_rad_s: np.ndarray,
    bias_accel_m_s2: np.ndarray,
    t0_ns: int,
    t1_ns: int,
    imu_t_ns: np.ndarray,
    imu_gyro_rad_s: np.ndarray,
    imu_accel_m_s2: np.ndarray,
    params: gtsam.PreintegrationCombinedParams,
    max_gap_s: float = 0.1,
) -> tuple[np.ndarray, np.ndarray] | None:
    """IMU-propagate a state (e.g. the latest ``Estimate``) from t0 to t1 in a z-up world.

    Returns (world_from_body 4x4, velocity) at t1, or None when the IMU does not cover
    [t0, t1]. For per-frame poses and pose priors in the front end (never waits on the back end).
    """
    if t1_ns == t0_ns:
        return np.asarray(world_from_body, float).copy(), np.asarray(velocity_world_m_s, float)
    pieces = integration_pieces(imu_t_ns, imu_gyro_rad_s, imu_accel_m_s2, t0_ns, t1_ns, max_gap_s)
    if pieces is None:
        return None
    bias = make_bias(bias_gyro_rad_s, bias_accel_m_s2)
    pim = gtsam.PreintegratedCombinedMeasurements(params, bias)
    integrate_pieces(pim, pieces)
    state = gtsam.NavState(
        gtsam.Pose3(np.asarray(world_from_body, float)), np.asarray(velocity_world_m_s, float)
    )
    pred = pim.predict(state, bias)
    return pred.pose().matrix(), np.asarray(pred.velocity(), float)

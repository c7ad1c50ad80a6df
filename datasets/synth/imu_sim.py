"""IMU measurements from a motion's analytic derivatives, plus noise and bias random walk.

Exact part: gyro = body angular velocity, accel = specific force ``R^T (a_world - g_world)``
with ``g_world = (0, 0, -g)`` (so a still, level IMU reads +g along its up axis).
Noise (Kalibr/EuRoC convention, continuous-time densities of :class:`ImuCalibration`):
white noise ``sigma = density / sqrt(dt)`` per sample, bias ``b[k+1] = b[k] + rw * sqrt(dt) * n``.
Deterministic for a given seed (numpy Generator).

:class:`ImuEffects` (all off by default) adds what a real rig's IMU also reads, before biases
and noise: ``meas = (I + S + M) @ exact + vibration``, per sensor (gyro, accel): ``S`` diagonal
scale errors and ``M`` an off-diagonal axis misalignment (small rotation plus shear), both drawn
once from the seed; vibration as from propellers: a narrow-band sinusoid near
``vibration_hz`` whose frequency wanders by ``vibration_bandwidth_hz`` (a slow random walk of
the motor speed), along a random fixed direction per sensor, with the given RMS. The
vibration is sampled at the IMU times as it is, so a frequency above the IMU's Nyquist rate
aliases (as in a real IMU without enough anti-alias filtering). Its displacement (micrometres at
tens of Hz) is not rendered into the images.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.signal import lfilter

from datasets.sequence import ImuArrays
from datasets.synth.trajectories import Motion
from slam.core.calibration import ImuCalibration


@dataclass(frozen=True)
class ImuEffects:
    """Mounting and vibration effects of a synthetic IMU (all off by default)."""

    vibration_accel_rms_m_s2: float = 0.0
    vibration_gyro_rms_rad_s: float = 0.0
    vibration_hz: float = 73.0
    vibration_bandwidth_hz: float = 1.5  # RMS wander of the vibration frequency
    scale_error_std: float = 0.0  # per axis, fraction (0.003 = 0.3 %)
    misalignment_std_rad: float = 0.0  # per off-diagonal element

    @property
    def active(self) -> bool:
        return self != ImuEffects()

    def validate(self) -> None:
        """InputError (one line, naming the parameter) for values outside their bounds."""
        from slam.core.errors import InputError

        bounds = {
            "vibration_accel_rms_m_s2": (0.0, 50.0),
            "vibration_gyro_rms_rad_s": (0.0, 5.0),
            "vibration_hz": (0.1, 2000.0),
            "vibration_bandwidth_hz": (0.0, 100.0),
            "scale_error_std": (0.0, 0.2),
            "misalignment_std_rad": (0.0, 0.1),
        }
        for name, (lo, hi) in bounds.items():
            v = getattr(self, name)
            if not lo <= v <= hi:
                raise InputError(f"IMU effect {name} = {v} is outside [{lo}, {hi}]")


def realistic_imu() -> ImuEffects:
    """The IMU half of ``--camera realistic``: a multirotor's propeller vibration (0.8 m/s^2
    and 0.02 rad/s RMS near 73 Hz), 0.3 % scale errors and 1 mrad axis misalignment."""
    return ImuEffects(
        vibration_accel_rms_m_s2=0.8,
        vibration_gyro_rms_rad_s=0.02,
        scale_error_std=0.003,
        misalignment_std_rad=0.001,
    )


@dataclass(frozen=True, eq=False)
class ImuDistortion:
    """The drawn effects: gyro/accel measurement matrices (3, 3) ``I + S + M`` and the
    vibration added to each sample (N, 3)."""

    gyro_matrix: np.ndarray
    accel_matrix: np.ndarray
    gyro_vibration_rad_s: np.ndarray
    accel_vibration_m_s2: np.ndarray


def draw_imu_distortion(effects: ImuEffects, t_s: np.ndarray, seed: int) -> ImuDistortion:
    """The effects' random parts for samples at ``t_s``, deterministic by ``seed`` (a stream of
    its own, so the IMU noise does not change when effects are switched on)."""
    rng = np.random.default_rng([seed, 17])
    mats = []
    for _ in range(2):
        m = np.eye(3) + np.diag(rng.standard_normal(3) * effects.scale_error_std)
        off = rng.standard_normal((3, 3)) * effects.misalignment_std_rad
        np.fill_diagonal(off, 0.0)
        mats.append(m + off)
    t = np.asarray(t_s, dtype=np.float64)
    n = len(t)
    vib = []
    for rms in (effects.vibration_gyro_rms_rad_s, effects.vibration_accel_rms_m_s2):
        direction = rng.standard_normal(3)
        direction /= np.linalg.norm(direction)
        phase0 = rng.uniform(0, 2 * np.pi)
        if rms <= 0 or n == 0:
            vib.append(np.zeros((n, 3)))
            continue
        # the motor speed wanders: an Ornstein-Uhlenbeck process with a 2 s time constant
        # (unit variance; the IMU's times are evenly spaced, so one AR(1) filter does it)
        dt = np.diff(t, prepend=t[0])
        a = float(np.exp(-float(np.median(dt[1:])) / 2.0)) if n > 1 else 0.0
        kicks = rng.standard_normal(n)
        kicks[0] /= np.sqrt(1 - a * a)  # start in the stationary distribution
        wander = lfilter([np.sqrt(1 - a * a)], [1.0, -a], kicks)
        freq_hz = effects.vibration_hz + effects.vibration_bandwidth_hz * wander
        phase = phase0 + 2 * np.pi * np.cumsum(freq_hz * dt)
        vib.append(np.sqrt(2.0) * rms * np.sin(phase)[:, None] * direction)
    return ImuDistortion(mats[0], mats[1], vib[0], vib[1])


@dataclass(frozen=True, eq=False)
class SimulatedImu:
    """The IMU stream, the true biases (N, 3) that were added to it, and the drawn effects."""

    arrays: ImuArrays
    gyro_bias_rad_s: np.ndarray
    accel_bias_m_s2: np.ndarray
    distortion: ImuDistortion | None = None


def exact_imu(
    motion: Motion, t_s: np.ndarray, gravity_m_s2: float
) -> tuple[np.ndarray, np.ndarray]:
    """Noise-free (gyro_rad_s, accel_m_s2), each (N, 3), at times ``t_s``."""
    ms = motion.sample(t_s)
    g_world = np.array([0.0, 0.0, -gravity_m_s2])
    specific_world = ms.accelerations_m_s2 - g_world
    accel = np.einsum("nji,nj->ni", ms.world_from_body_rot, specific_world)
    return ms.omega_body_rad_s, accel


def simulate_imu(
    motion: Motion,
    t_ns: np.ndarray,
    t0_s: float,
    calib: ImuCalibration,
    *,
    noise: bool = True,
    seed: int = 0,
    gyro_bias0_rad_s: np.ndarray | None = None,
    accel_bias0_m_s2: np.ndarray | None = None,
    effects: ImuEffects | None = None,
) -> SimulatedImu:
    """IMU samples at ``t_ns`` (int64; the motion is evaluated at ``t0_s + (t_ns - t_ns[0])``).

    ``noise=False`` gives the exact measurements plus the (constant) initial biases (and the
    ``effects``, which are not noise: scale, misalignment, vibration).
    """
    t_ns = np.asarray(t_ns, dtype=np.int64)
    n = len(t_ns)
    t_s = t0_s + (t_ns - t_ns[0]).astype(np.float64) * 1e-9
    gyro, accel = exact_imu(motion, t_s, calib.gravity_m_s2)
    distortion = None
    if effects is not None and effects.active:
        distortion = draw_imu_distortion(effects, t_s, seed)
        gyro = gyro @ distortion.gyro_matrix.T + distortion.gyro_vibration_rad_s
        accel = accel @ distortion.accel_matrix.T + distortion.accel_vibration_m_s2
    bg = np.tile(np.zeros(3) if gyro_bias0_rad_s is None else gyro_bias0_rad_s, (n, 1))
    ba = np.tile(np.zeros(3) if accel_bias0_m_s2 is None else accel_bias0_m_s2, (n, 1))
    if noise and n:
        rng = np.random.default_rng(seed)
        dt = 1.0 / calib.rate_hz
        white_g = rng.standard_normal((n, 3)) * (calib.gyro_noise_density / np.sqrt(dt))
        white_a = rng.standard_normal((n, 3)) * (calib.accel_noise_density / np.sqrt(dt))
        steps_g = rng.standard_normal((n, 3)) * (calib.gyro_random_walk * np.sqrt(dt))
        steps_a = rng.standard_normal((n, 3)) * (calib.accel_random_walk * np.sqrt(dt))
        steps_g[0] = 0.0
        steps_a[0] = 0.0
        bg = bg + np.cumsum(steps_g, axis=0)
        ba = ba + np.cumsum(steps_a, axis=0)
        gyro = gyro + bg + white_g
        accel = accel + ba + white_a
    else:
        gyro = gyro + bg
        accel = accel + ba
    return SimulatedImu(
        arrays=ImuArrays(t_ns=t_ns, gyro_rad_s=gyro, accel_m_s2=accel),
        gyro_bias_rad_s=bg,
        accel_bias_m_s2=ba,
        distortion=distortion,
    )


def read_imu_csv(path: str, t_from_ns: int | None = None, t_to_ns: int | None = None) -> ImuArrays:
    """A EuRoC ``imu0/data.csv`` (t_ns, gyro xyz rad/s, accel xyz m/s^2), optionally clipped."""
    from pathlib import Path

    from slam.core.errors import InputError

    p = Path(path)
    if not p.is_file():
        raise InputError(f"IMU csv not found: {p}")
    rows = [
        ln for ln in p.read_text().splitlines() if ln.strip() and not ln.lstrip().startswith("#")
    ]
    try:
        t_ns = np.array([int(r.split(",")[0]) for r in rows], dtype=np.int64)
        vals = np.array([[float(v) for v in r.split(",")[1:7]] for r in rows])
    except (ValueError, IndexError) as exc:
        raise InputError(f"{p}: not a EuRoC IMU csv (t_ns, wx, wy, wz, ax, ay, az): {exc}") from exc
    if vals.ndim != 2 or vals.shape[1] != 6:
        raise InputError(f"{p}: expected 7 columns (t_ns, wx, wy, wz, ax, ay, az)")
    order = np.argsort(t_ns, kind="stable")
    t_ns, vals = t_ns[order], vals[order]
    keep = np.concatenate([[True], np.diff(t_ns) > 0]) if len(t_ns) else np.zeros(0, bool)
    if t_from_ns is not None:
        keep &= t_ns >= t_from_ns
    if t_to_ns is not None:
        keep &= t_ns <= t_to_ns
    return ImuArrays(t_ns=t_ns[keep], gyro_rad_s=vals[keep, :3], accel_m_s2=vals[keep, 3:6])


REAL_BIAS_WINDOW_S = 10.0
"""The real IMU's errors (real less the trajectory's exact readings) averaged over this window
are its bias profile, kept by :func:`real_imu_errors_on_motion`."""
REAL_NOISE_WINDOW_S = 0.2
"""The errors less their average over this window (above ~5 Hz, where a 20 Hz trajectory has no
motion) are its noise and vibration, kept too."""


def _moving_average(values: np.ndarray, window: int) -> np.ndarray:
    """Centred moving average along axis 0 over ``window`` samples, the edges averaged over
    the samples there are (no padding)."""
    if window <= 1:
        return values.copy()
    csum = np.concatenate([np.zeros((1,) + values.shape[1:]), np.cumsum(values, axis=0)])
    n = len(values)
    lo = np.clip(np.arange(n) - window // 2, 0, n)
    hi = np.clip(np.arange(n) + (window - window // 2), 0, n)
    return (csum[hi] - csum[lo]) / (hi - lo).reshape((-1,) + (1,) * (values.ndim - 1))


def real_imu_errors_on_motion(
    motion: Motion,
    real: ImuArrays,
    motion_t0_ns: int,
    calib: ImuCalibration,
    seed: int = 0,
) -> ImuArrays:
    """An IMU that agrees with ``motion`` (the trajectory the images follow) and keeps a real
    IMU's error profile: at the real samples' times, the exact readings of ``motion``, plus the
    real stream's errors against them (real less exact) averaged over ``REAL_BIAS_WINDOW_S``
    (its bias drift, below ~0.1 Hz), plus those errors less their ``REAL_NOISE_WINDOW_S``
    average (its noise and vibration, above ~5 Hz), plus white noise of ``calib``'s densities
    (the sensor noise of the band in between). The band dropped in between is where the motion
    is: there the real IMU and the trajectory disagree by what neither describes (EuRoC V1_01:
    an accelerometer scale of 1.008 against OpenVINS's ground truth, and a bias that vicon2gt
    sees wander 0.03-0.18 m/s^2 within 10 s; BENCHMARKS.md, "branch v101imu18").
    ``motion`` is evaluated at ``(t_ns - motion_t0_ns)`` s."""
    t_ns = np.asarray(real.t_ns, np.int64)
    t_s = (t_ns - int(motion_t0_ns)).astype(np.float64) * 1e-9
    gyro, accel = exact_imu(motion, t_s, calib.gravity_m_s2)
    rate_hz = 1.0 / float(np.median(np.diff(t_s))) if len(t_s) > 1 else calib.rate_hz
    bias_n = max(1, int(round(REAL_BIAS_WINDOW_S * rate_hz)))
    noise_n = max(1, int(round(REAL_NOISE_WINDOW_S * rate_hz)))
    rng = np.random.default_rng(seed)
    out = []
    for exact, meas, density in (
        (gyro, real.gyro_rad_s, calib.gyro_noise_density),
        (accel, real.accel_m_s2, calib.accel_noise_density),
    ):
        err = np.asarray(meas, np.float64) - exact
        slow = _moving_average(err, bias_n)
        fast = err - _moving_average(err, noise_n)
        white = rng.standard_normal(exact.shape) * (density * np.sqrt(rate_hz))
        out.append(exact + slow + fast + white)
    return ImuArrays(t_ns=t_ns, gyro_rad_s=out[0], accel_m_s2=out[1])

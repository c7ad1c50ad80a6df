"""IMU measurements from a motion's analytic derivatives, plus noise and bias random walk.

Exact part: gyro = body angular velocity, accel = specific force ``R^T (a_world - g_world)``
with ``g_world = (0, 0, -g)`` (so a still, level IMU reads +g along its up axis).
Noise (Kalibr/EuRoC convention, continuous-time densities of :class:`ImuCalibration`):
white noise ``sigma = density / sqrt(dt)`` per sample, bias ``b[k+1] = b[k] + rw * sqrt(dt) * n``.
Deterministic for a given seed (numpy Generator).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from datasets.sequence import ImuArrays
from datasets.synth.trajectories import Motion
from slam.core.calibration import ImuCalibration


@dataclass(frozen=True, eq=False)
class SimulatedImu:
    """The IMU stream and the true biases (N, 3) that were added to it."""

    arrays: ImuArrays
    gyro_bias_rad_s: np.ndarray
    accel_bias_m_s2: np.ndarray


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
) -> SimulatedImu:
    """IMU samples at ``t_ns`` (int64; the motion is evaluated at ``t0_s + (t_ns - t_ns[0])``).

    ``noise=False`` gives the exact measurements plus the (constant) initial biases.
    """
    t_ns = np.asarray(t_ns, dtype=np.int64)
    n = len(t_ns)
    t_s = t0_s + (t_ns - t_ns[0]).astype(np.float64) * 1e-9
    gyro, accel = exact_imu(motion, t_s, calib.gravity_m_s2)
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

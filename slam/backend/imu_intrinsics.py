"""Online IMU intrinsics: per-sensor 3x3 correction matrices (scale and axis misalignment)
fitted to the back end's smoothed keyframe states.

A real IMU's gyro and accelerometer read ``raw = T @ true + bias`` with ``T`` a few tenths of
a percent off the identity (per-axis scale, axis misalignment). GTSAM's preintegration takes
calibrated readings, so the correction lives outside the graph, as OpenVINS keeps it in its
state: this module estimates ``C ~= T^-1`` per sensor and the IMU store applies it to every
reading (``slam.imu_buffer.ImuBuffer.set_intrinsics``), before the biases are taken off.

The fit, over the keyframe states of the last ``imu_intrinsics_window_s`` once the smoother
has let them go (final, vision-anchored estimates), against the raw IMU between them, joined
into intervals of at least ``imu_intrinsics_interval_s``:

1. gyro (Gauss-Newton, a few iterations): the preintegrated rotation of ``C_g @ raw - b_g``
   over each interval against the states' relative rotation ``R_a^T R_b``; unknowns ``C_g``
   (9) and a bias ``b_g`` constant over the window.
2. accelerometer (linear, given the gyro's rotations, taken at each piece's middle): per
   interval a -> b of length T, ``R_a^T (v_b - v_a - g T) = sum_k R_ak (C_a a_k - b_a) dt_k``
   and ``R_a^T (p_b - p_a - v_a T - g T^2 / 2) = sum_k R_ak (C_a a_k - b_a) w_k`` (``w_k``
   the double integral's weight of piece k); unknowns ``C_a`` (9), every state's velocity and
   a bias per interval that follows the calibration's random walk (the states' positions and
   rotations are the anchors).

Both hold ``C - I`` to 0 with ``imu_intrinsics_prior_sigma`` (a weakly excited direction
stays at the identity; its bias takes it) and weigh each equation kind by its residual
RMS. A sensor's matrix is applied once the standard deviation of each of its three scale
factors is below ``imu_intrinsics_apply_std`` (excitation gate) and, the first time, one of
them is at least ``imu_intrinsics_min_correction`` from 1 (a calibrated IMU stays as read);
it is re-fitted every ``imu_intrinsics_every_s``. Tested against injected truth in
``tests/test_imu_intrinsics.py``; measured in BENCHMARKS.md (imu17).
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass
from typing import Any

import numpy as np

from slam.backend.config import BackendConfig
from slam.core.calibration import ImuCalibration
from slam.core.geometry import so3_exp_batch, so3_log
from slam.core.messages import ImuIntrinsics

_BIAS_PRIOR_GYRO_RAD_S = 0.1  # nearly free: the window's constant biases
_BIAS_PRIOR_ACCEL_M_S2 = 1.0
_GN_ITERATIONS = 3


@dataclass(frozen=True, eq=False)
class KeyframeState:
    """A final (marginalised) keyframe state of the smoother, and the raw IMU pieces since the
    previous one (``slam.backend.imu.integration_pieces`` of the uncorrected readings; None
    when the two were not joined by an IMU factor)."""

    t_ns: int
    world_from_body_rot: np.ndarray  # (3, 3)
    position_world_m: np.ndarray  # (3,)
    velocity_world_m_s: np.ndarray  # (3,)
    pieces_from_previous: tuple[np.ndarray, np.ndarray, np.ndarray] | None


@dataclass(frozen=True, eq=False)
class IntrinsicsFit:
    """One fit: each sensor's matrix, bias and the standard deviations of the matrix entries."""

    t_ns: int
    gyro_matrix: np.ndarray  # (3, 3)
    accel_matrix: np.ndarray  # (3, 3)
    gyro_std: np.ndarray  # (3, 3)
    accel_std: np.ndarray  # (3, 3)
    bias_gyro_rad_s: np.ndarray
    bias_accel_m_s2: np.ndarray
    intervals: int
    rms_rotation_rad: float
    rms_velocity_m_s: float
    rms_position_m: float


class OnlineImuIntrinsics:
    """Collects final keyframe states, fits the IMU's correction matrices, gates them."""

    def __init__(self, config: BackendConfig, imu: ImuCalibration) -> None:
        self.config = config
        self.gravity_world_m_s2 = np.array([0.0, 0.0, -imu.gravity_m_s2])
        self.accel_random_walk = imu.accel_random_walk
        self._states: deque[KeyframeState] = deque()
        self._last_fit_ns: int | None = None
        self.fits: list[IntrinsicsFit] = []
        self.applied = ImuIntrinsics.identity()
        self.gyro_applied_t_ns = -1  # the first fit applied (sensor time), -1: none yet
        self.accel_applied_t_ns = -1
        self.status = "collecting"

    # --- input -----------------------------------------------------------------------------------
    def add_state(self, state: KeyframeState) -> None:
        """A keyframe state the smoother let go (time order)."""
        if self._states and state.t_ns <= self._states[-1].t_ns:
            return
        self._states.append(state)
        window_ns = int(self.config.imu_intrinsics_window_s * 1e9)
        while self._states and self._states[0].t_ns < state.t_ns - window_ns:
            self._states.popleft()

    def update(self) -> ImuIntrinsics | None:
        """Fit again if it is time; the newly applied intrinsics when they changed, else None."""
        if not self._states:
            return None
        cfg = self.config
        t_now = self._states[-1].t_ns
        if (
            self._last_fit_ns is not None
            and t_now - self._last_fit_ns < cfg.imu_intrinsics_every_s * 1e9
        ):
            return None
        span_s = (t_now - self._states[0].t_ns) * 1e-9
        if span_s < cfg.imu_intrinsics_min_span_s:
            return None
        self._last_fit_ns = t_now
        fit = fit_intrinsics(
            list(self._states),
            self.gravity_world_m_s2,
            self.applied,
            cfg.imu_intrinsics_prior_sigma,
            cfg.imu_intrinsics_misalignment,
            cfg.imu_intrinsics_interval_s,
            self.accel_random_walk,
        )
        if fit is None:
            self.status = "too few intervals"
            return None
        self.fits.append(fit)
        limit = cfg.imu_intrinsics_apply_std
        gyro_ok = float(np.diag(fit.gyro_std).max()) < limit
        accel_ok = float(np.diag(fit.accel_std).max()) < limit and cfg.imu_intrinsics_accel
        if not (gyro_ok or accel_ok):
            self.status = "too little excitation"
            return None
        # a sensor is corrected at all only once its fit is clearly off the identity
        least = cfg.imu_intrinsics_min_correction
        if self.gyro_applied_t_ns < 0:
            gyro_ok = gyro_ok and _largest_scale_error(fit.gyro_matrix) >= least
        if self.accel_applied_t_ns < 0:
            accel_ok = accel_ok and _largest_scale_error(fit.accel_matrix) >= least
        if not (gyro_ok or accel_ok):
            if self.applied.is_identity:
                self.status = "calibrated (within imu_intrinsics_min_correction)"
            return None
        gyro = fit.gyro_matrix if gyro_ok else self.applied.gyro_matrix
        accel = fit.accel_matrix if accel_ok else self.applied.accel_matrix
        if gyro_ok and self.gyro_applied_t_ns < 0:
            self.gyro_applied_t_ns = t_now
        if accel_ok and self.accel_applied_t_ns < 0:
            self.accel_applied_t_ns = t_now
        self.status = (
            "applied" if gyro_ok and accel_ok else ("gyro applied" if gyro_ok else "accel applied")
        )
        self.applied = ImuIntrinsics(gyro_matrix=gyro, accel_matrix=accel)
        return self.applied

    @property
    def converged(self) -> bool:
        return self.gyro_applied_t_ns >= 0 and self.accel_applied_t_ns >= 0

    def summary(self) -> dict[str, Any]:
        """For stats.json: the applied matrices, the last fit and its history (scales)."""
        last = self.fits[-1] if self.fits else None
        out: dict[str, Any] = {
            "status": self.status,
            "fits": len(self.fits),
            "gyro_matrix": self.applied.gyro_matrix.round(6).tolist(),
            "accel_matrix": self.applied.accel_matrix.round(6).tolist(),
            "gyro_applied_t_ns": self.gyro_applied_t_ns,
            "accel_applied_t_ns": self.accel_applied_t_ns,
        }
        if last is not None:
            out["last_fit"] = {
                "t_ns": last.t_ns,
                "intervals": last.intervals,
                "gyro_std": last.gyro_std.round(7).tolist(),
                "accel_std": last.accel_std.round(7).tolist(),
                "bias_gyro_rad_s": last.bias_gyro_rad_s.round(6).tolist(),
                "bias_accel_m_s2": last.bias_accel_m_s2.round(5).tolist(),
                "rms_rotation_rad": last.rms_rotation_rad,
                "rms_velocity_m_s": last.rms_velocity_m_s,
                "rms_position_m": last.rms_position_m,
            }
            out["history"] = [
                {
                    "t_ns": f.t_ns,
                    "gyro_scale": np.diag(f.gyro_matrix).round(6).tolist(),
                    "accel_scale": np.diag(f.accel_matrix).round(6).tolist(),
                    "gyro_scale_std": np.diag(f.gyro_std).round(7).tolist(),
                    "accel_scale_std": np.diag(f.accel_std).round(7).tolist(),
                }
                for f in self.fits
            ]
        return out


def _largest_scale_error(matrix: np.ndarray) -> float:
    return float(np.abs(np.diag(matrix) - 1.0).max())


# --- the fit ---------------------------------------------------------------------------------------
@dataclass(frozen=True, eq=False)
class _Intervals:
    """The fit's intervals: state indices (M,) a and b, and their raw IMU pieces padded to one
    length (M, P) with zero-length pieces (which add nothing)."""

    a: np.ndarray
    b: np.ndarray
    dt_s: np.ndarray  # (M, P)
    gyro_rad_s: np.ndarray  # (M, P, 3)
    accel_m_s2: np.ndarray  # (M, P, 3)


def _intervals(states: list[KeyframeState], interval_s: float) -> _Intervals | None:
    """Consecutive states joined by IMU pieces, grouped into intervals of at least
    ``interval_s`` (a longer interval: the accelerometer's error grows with its square, the
    states' noise does not)."""
    found: list[tuple[int, int, list[tuple[np.ndarray, np.ndarray, np.ndarray]]]] = []
    a = 0
    run: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []
    span_s = 0.0
    for i in range(1, len(states)):
        pieces = states[i].pieces_from_previous
        if pieces is None or len(pieces[0]) == 0:
            a, run, span_s = i, [], 0.0
            continue
        run.append(pieces)
        span_s += float(pieces[0].sum())
        if span_s >= interval_s:
            found.append((a, i, run))
            a, run, span_s = i, [], 0.0
    if not found:
        return None
    lengths = [sum(len(p[0]) for p in r) for _, _, r in found]
    m, width = len(found), max(lengths)
    dt = np.zeros((m, width))
    gyro = np.zeros((m, width, 3))
    accel = np.zeros((m, width, 3))
    for j, (_, _, r) in enumerate(found):
        n = lengths[j]
        dt[j, :n] = np.concatenate([p[0] for p in r])
        gyro[j, :n] = np.concatenate([p[1] for p in r])
        accel[j, :n] = np.concatenate([p[2] for p in r])
    return _Intervals(
        np.array([f[0] for f in found]), np.array([f[1] for f in found]), dt, gyro, accel
    )


def _prefix_rotations(iv: _Intervals, gyro_matrix: np.ndarray, bias: np.ndarray) -> np.ndarray:
    """(M, P + 1, 3, 3): body(a)_from_body(start of piece k) per interval, the last entry the
    whole interval's rotation, integrating ``gyro_matrix @ raw - bias``."""
    m, width = iv.dt_s.shape
    omega = iv.gyro_rad_s @ gyro_matrix.T - bias
    steps = so3_exp_batch((omega * iv.dt_s[..., None]).reshape(-1, 3)).reshape(m, width, 3, 3)
    prefix = np.empty((m, width + 1, 3, 3))
    prefix[:, 0] = np.eye(3)
    for k in range(width):
        prefix[:, k + 1] = prefix[:, k] @ steps[:, k]
    return prefix


def _kron_rows(left: np.ndarray, vec: np.ndarray, weight: np.ndarray) -> np.ndarray:
    """Per interval sum_k weight_k * left_k @ kron(I3, vec_k^T): the (M, 3, 9) derivative of
    ``sum_k weight_k * left_k @ (E @ vec_k)`` by the row-major entries of E."""
    m = left.shape[0]
    return np.einsum("mkri,mkc,mk->mric", left, vec, weight).reshape(m, 3, 9)


def fit_intrinsics(
    states: list[KeyframeState],
    gravity_world_m_s2: np.ndarray,
    start: ImuIntrinsics,
    prior_sigma: float,
    misalignment: bool = True,
    interval_s: float = 0.5,
    accel_random_walk: float = 3e-3,
) -> IntrinsicsFit | None:
    """Fit both sensors' matrices to ``states`` (module docstring), starting from ``start``;
    None with fewer than 10 intervals of ``interval_s``. ``misalignment``: False fits the
    diagonals (scales) only, the off-diagonal entries held at the identity's."""
    iv = _intervals(states, interval_s)
    if iv is None or len(iv.a) < 10:
        return None
    m = len(iv.a)
    mask = np.ones(9, bool) if misalignment else np.eye(3, dtype=bool).reshape(9)
    prior = np.where(mask, 1.0 / prior_sigma**2, 1e12)
    rot = np.array([s.world_from_body_rot for s in states])
    rel = np.einsum("mji,mjk->mik", rot[iv.a], rot[iv.b])  # R_a^T R_b
    # --- gyro: Gauss-Newton on the rotation residuals Log(dR^T R_a^T R_b) ------------------
    gm = np.array(start.gyro_matrix, dtype=float)
    bg = np.zeros(3)
    h = np.eye(12)
    rms_rot = 0.0
    for _ in range(_GN_ITERATIONS):
        prefix = _prefix_rotations(iv, gm, bg)
        d_rot = prefix[:, -1]
        r0 = so3_log(np.einsum("mji,mjk->mik", d_rot, rel)).reshape(m, 3)
        # perturbing piece k's rate by d: dR -> dR Exp(dR^T prefix_(k+1) d dt_k)
        left = np.einsum("mji,mkjl->mkil", d_rot, prefix[:, 1:])
        jac = np.zeros((m, 3, 12))
        jac[:, :, :9] = -_kron_rows(left, iv.gyro_rad_s, iv.dt_s)
        jac[:, :, 9:] = np.einsum("mkij,mk->mij", left, iv.dt_s)
        rms_rot = float(np.sqrt(np.mean(r0**2)))
        w = 1.0 / max(rms_rot, 1e-7) ** 2
        h = np.einsum("mri,mrj->ij", jac, jac) * w
        g = -np.einsum("mri,mr->i", jac, r0) * w
        h[:9, :9] += np.diag(prior)
        g[:9] -= prior * (gm - np.eye(3)).reshape(9)
        h[9:, 9:] += np.eye(3) / _BIAS_PRIOR_GYRO_RAD_S**2
        g[9:] -= bg / _BIAS_PRIOR_GYRO_RAD_S**2
        delta = np.linalg.solve(h, g)
        gm = gm + delta[:9].reshape(3, 3)
        bg = bg + delta[9:]
    gyro_std = np.sqrt(np.clip(np.diag(np.linalg.inv(h))[:9], 0, None)).reshape(3, 3)
    # --- accelerometer: linear in E_a, the states' velocities and each interval's bias --------
    # Per interval two 3-row equations over 18 unknowns: E_a (9), v_a, v_b, b_a (3 each); the
    # bias follows a random walk from one interval to the next (the calibration's: 3e-3
    # m/s^2/sqrt(s) moves it 0.013 m/s^2 in 20 s, as much as a 0.13 % scale error of gravity).
    # The normal equations are assembled block by block.
    ends = np.unique(np.concatenate([iv.a, iv.b]))
    slot = {int(s): j for j, s in enumerate(ends.tolist())}
    n_v = 3 * len(ends)
    n = 9 + n_v + 3 * m
    prefix = _prefix_rotations(iv, gm, bg)
    # body(a)_from_body(middle of piece k): the midpoint rule (the piece's start, a first-order
    # rule, is off by half a piece's rotation times the specific force: at 3 rad/s, 200 Hz and
    # 10 m/s^2 a bias of 0.07 m/s^2 along omega x a, more than the scale errors sought)
    omega = iv.gyro_rad_s @ gm.T - bg
    half = so3_exp_batch((0.5 * omega * iv.dt_s[..., None]).reshape(-1, 3))
    rot_k = prefix[:, :-1] @ half.reshape(prefix[:, :-1].shape)
    dt = iv.dt_s
    span = dt.sum(axis=1)
    wgt = (span[:, None] - np.cumsum(dt, axis=1)) * dt + 0.5 * dt**2  # double integral
    ra_t = np.transpose(rot[iv.a], (0, 2, 1))
    pos = np.array([s.position_world_m for s in states])
    g_w = gravity_world_m_s2
    ia = 9 + 3 * np.array([slot[int(s)] for s in iv.a])
    ib = 9 + 3 * np.array([slot[int(s)] for s in iv.b])
    ibias = 9 + n_v + 3 * np.arange(m)
    cols = np.concatenate(
        [
            np.tile(np.arange(9), (m, 1)),
            ia[:, None] + np.arange(3),
            ib[:, None] + np.arange(3),
            ibias[:, None] + np.arange(3),
        ],
        axis=1,
    )
    local_v = np.zeros((m, 3, 18))
    local_p = np.zeros((m, 3, 18))
    # R_a^T v_b - R_a^T v_a - [sum R_ak E a_k dt] + [sum R_ak dt] b_a
    #   = R_a^T g T + sum R_ak a_k dt
    local_v[:, :, :9] = -_kron_rows(rot_k, iv.accel_m_s2, dt)
    local_v[:, :, 9:12] = -ra_t
    local_v[:, :, 12:15] = ra_t
    local_v[:, :, 15:18] = np.einsum("mkij,mk->mij", rot_k, dt)
    y_v = (ra_t @ g_w) * span[:, None] + np.einsum("mkij,mkj,mk->mi", rot_k, iv.accel_m_s2, dt)
    # -R_a^T v_a T - [sum R_ak E a_k w] + [sum R_ak w] b_a
    #   = -R_a^T (p_b - p_a) + R_a^T g T^2 / 2 + sum R_ak a_k w
    local_p[:, :, :9] = -_kron_rows(rot_k, iv.accel_m_s2, wgt)
    local_p[:, :, 9:12] = -ra_t * span[:, None, None]
    local_p[:, :, 15:18] = np.einsum("mkij,mk->mij", rot_k, wgt)
    y_p = (
        -np.einsum("mij,mj->mi", ra_t, pos[iv.b] - pos[iv.a])
        + 0.5 * (ra_t @ g_w) * (span**2)[:, None]
        + np.einsum("mkij,mkj,mk->mi", rot_k, iv.accel_m_s2, wgt)
    )
    # the bias's random walk between consecutive intervals of one chain
    joined = np.flatnonzero(iv.b[:-1] == iv.a[1:])
    walk_w = 1.0 / (max(accel_random_walk, 1e-9) ** 2 * 0.5 * (span[joined] + span[joined + 1]))
    sig_v, sig_p = 1e-2, 1e-3
    x: np.ndarray = np.zeros(n)
    h_a = np.eye(n)
    rows = np.repeat(cols[:, :, None], 18, axis=2)
    cols_t = np.repeat(cols[:, None, :], 18, axis=1)
    for _ in range(2):  # the second pass weighs each kind by its residual RMS
        blocks = (
            np.einsum("mri,mrj->mij", local_v, local_v) / sig_v**2
            + np.einsum("mri,mrj->mij", local_p, local_p) / sig_p**2
        )
        vecs = (
            np.einsum("mri,mr->mi", local_v, y_v) / sig_v**2
            + np.einsum("mri,mr->mi", local_p, y_p) / sig_p**2
        )
        h_a = np.zeros((n, n))
        np.add.at(h_a, (rows, cols_t), blocks)
        rhs = np.zeros(n)
        np.add.at(rhs, cols, vecs)
        h_a[:9, :9] += np.diag(prior)
        diag = np.arange(9 + n_v, n)
        h_a[diag, diag] += 1.0 / _BIAS_PRIOR_ACCEL_M_S2**2
        for j, w in zip(joined.tolist(), walk_w.tolist(), strict=True):
            for c in range(3):
                p_, q_ = ibias[j] + c, ibias[j + 1] + c
                h_a[p_, p_] += w
                h_a[q_, q_] += w
                h_a[p_, q_] -= w
                h_a[q_, p_] -= w
        x = np.linalg.solve(h_a, rhs)
        xl = x[cols]
        res_v = np.einsum("mri,mi->mr", local_v, xl) - y_v
        res_p = np.einsum("mri,mi->mr", local_p, xl) - y_p
        sig_v = max(float(np.sqrt(np.mean(res_v**2))), 1e-6)
        sig_p = max(float(np.sqrt(np.mean(res_p**2))), 1e-7)
    unit = np.zeros((n, 9))
    unit[:9, :9] = np.eye(9)
    accel_std = np.sqrt(np.clip(np.diag(np.linalg.solve(h_a, unit)[:9]), 0, None)).reshape(3, 3)
    bias_accel = x[9 + n_v + 3 * (m - 1) : 9 + n_v + 3 * m]  # the newest interval's
    return IntrinsicsFit(
        t_ns=states[-1].t_ns,
        gyro_matrix=gm,
        accel_matrix=np.eye(3) + x[:9].reshape(3, 3),
        gyro_std=gyro_std,
        accel_std=accel_std,
        bias_gyro_rad_s=bg,
        bias_accel_m_s2=bias_accel,
        intervals=m,
        rms_rotation_rad=rms_rot,
        rms_velocity_m_s=sig_v,
        rms_position_m=sig_p,
    )

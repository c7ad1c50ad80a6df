"""The camera-IMU time offset, estimated online from the keyframes and the gyro.

Convention as the calibration's: an image stamped ``t`` (camera stamp, the calibration's offset
already applied) shows the scene at IMU time ``t + d``; ``d`` is the residual offset estimated
here. Once it is known well enough (``time_offset_apply_std_ms``) the player stamps every frame
``t + d`` (:func:`slam.runtime.player.restamped`), so the whole pipeline (front end, IMU
preintegration between keyframes, outputs) runs in the IMU clock; each keyframe says which
offset its stamp carries (``Keyframe.time_offset_ns``), so the estimate is always made against
the raw stamps and does not feed back on itself.

Measurement: each pair of consecutive keyframes of one map segment gives the camera's relative
rotation ``R_vis`` (body frame, from the front end's poses, the previous one as moved by the
corrections since: both in one frame), and the gyro gives ``R_gyro(t0 + d, t1 + d)``, read off
an attitude track (the raw gyro integrated sample by sample, trapezoidal). The residual
``log(R_vis^T R_gyro(d)) - T b`` (``T`` the pair's duration, ``b`` a residual gyro bias
estimated along) is minimised over ``d`` and ``b`` on the pairs of the last
``time_offset_window_s``: a grid search over the bound until the first estimate is applied, then
Gauss-Newton (numeric derivative in ``d``), Huber weights, a Gaussian prior on ``d`` around 0
(the calibration's). The spread is from the normal equations with the robust residual scale.

Why not a state of the smoother (VINS-Fusion shifts every observation by ``td`` times its image
velocity inside the projection factor): our landmarks are GTSAM smart factors, which take fixed
measurements, and a Python ``CustomFactor`` per observation would multiply the back end's cost.
The rotation model needs no landmarks and is what ``slam calib check`` measures offline.

Hand-written: nothing off the shelf estimates this from a stream of keyframes. Quaternions in
plain numpy (scipy's ``Rotation`` objects cost ~50 us each to build: 0.4 s a keyframe, measured).
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from slam.backend.config import BackendConfig
from slam.core.messages import ImuSample, Keyframe, TimeOffsetState

_H_S = 1e-3  # numeric derivative step in d
_GRID_S = 1e-3  # grid step of the initial search
_BIAS_PRIOR_RAD_S = 0.1
_MIN_NOISE_RAD = 1e-5
# A pair turning faster than this starts the back end's hold (``time_offset_hold_s``): the
# first hint of motion, well above a still rig's visual jitter (~1 mrad/s). 0.2 rad/s let the
# keyframes of the motion's first 0.3 s in with camera stamps: at +20 ms live ATE 1.29 vs 0.36 cm
# with 0.05 (BENCHMARKS.md, 2026-12-02, time offset from the motion's start).
_MOVING_RAD_S = 0.05


def _qmul(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Hamilton product of (..., 4) wxyz quaternions."""
    aw, ax, ay, az = a[..., 0], a[..., 1], a[..., 2], a[..., 3]
    bw, bx, by, bz = b[..., 0], b[..., 1], b[..., 2], b[..., 3]
    return np.stack(
        [
            aw * bw - ax * bx - ay * by - az * bz,
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
        ],
        axis=-1,
    )


def _qconj(q: np.ndarray) -> np.ndarray:
    return q * np.array([1.0, -1.0, -1.0, -1.0])


def _qexp(rotvec: np.ndarray) -> np.ndarray:
    """wxyz quaternion of (..., 3) rotation vectors."""
    angle = np.linalg.norm(rotvec, axis=-1, keepdims=True)
    half = 0.5 * angle
    # sin(x/2)/x, its series below 1e-4 rad
    k = np.where(angle > 1e-4, np.sin(half) / np.maximum(angle, 1e-300), 0.5 - angle**2 / 48)
    return np.concatenate([np.cos(half), rotvec * k], axis=-1)


def _qlog(q: np.ndarray) -> np.ndarray:
    """(..., 3) rotation vectors of wxyz quaternions (shortest rotation)."""
    q = np.where(q[..., :1] < 0, -q, q)
    v = q[..., 1:]
    s = np.linalg.norm(v, axis=-1, keepdims=True)
    angle = 2 * np.arctan2(s, q[..., :1])
    k = np.where(s > 1e-12, angle / np.maximum(s, 1e-300), 2.0 / np.maximum(q[..., :1], 1e-300))
    return np.asarray(v * k)


@dataclass(frozen=True)
class _Pair:
    t0_ns: int  # raw (camera) stamps of the two keyframes
    t1_ns: int
    vis_wxyz: np.ndarray  # body(t0)_from_body(t1), from the images


class OnlineTimeOffset:
    """Feed it every IMU sample (:meth:`add_imu`) and every keyframe (:meth:`add_keyframe`);
    read :meth:`state`. Synchronous, no threads; owned by ``VioBackend``."""

    def __init__(self, config: BackendConfig) -> None:
        self.config = config
        self.max_s = config.time_offset_max_ms * 1e-3
        self._pending: list[ImuSample] = []
        self._t = np.zeros(0, np.int64)
        self._rot = np.zeros((0, 4))  # attitude track, wxyz
        self._gyro = np.zeros((0, 3))
        self._last: tuple[int, int, int, np.ndarray] | None = None  # kf id, segment, t_raw, pose
        self._waiting: deque[_Pair] = deque()  # the gyro does not cover them yet
        self._pairs: deque[_Pair] = deque()
        self.offset_s = 0.0
        self.std_s = float("inf")
        self.bias_rad_s = np.zeros(3)
        self.applied_ns = 0
        self.status = "waiting for motion"
        self.updates = 0
        self.history: list[tuple[float, float, float, float]] = []  # t_s, est, std, applied (ms)
        self._t_first_ns: int | None = None
        self._locked = False
        self.moving = False  # the last pair turned faster than _MOVING_RAD_S

    # --- input ---------------------------------------------------------------------------------
    def add_imu(self, sample: ImuSample) -> None:
        self._pending.append(sample)

    def add_keyframe(self, kf: Keyframe) -> None:
        """Make a pair with the previous keyframe (same segment), then re-estimate."""
        t_raw = int(kf.t_ns) - int(kf.time_offset_ns)
        if self._t_first_ns is None:
            self._t_first_ns = t_raw
        prev_pose = kf.previous_keyframe_world_from_body
        last = self._last
        if (
            last is not None
            and prev_pose is not None
            and last[0] == kf.previous_keyframe_id
            and last[1] == kf.segment_id
            and t_raw > last[2]
        ):
            rel = np.asarray(prev_pose)[:3, :3].T @ np.asarray(kf.world_from_body_vo)[:3, :3]
            if np.all(np.isfinite(rel)):
                rot = Rotation.from_matrix(rel)
                xyzw = rot.as_quat()
                rate = float(np.linalg.norm(rot.as_rotvec())) / ((t_raw - last[2]) * 1e-9)
                self.moving = rate > _MOVING_RAD_S
                self._waiting.append(_Pair(last[2], t_raw, np.roll(xyzw, 1)))
        self._last = (kf.keyframe_id, kf.segment_id, t_raw, np.asarray(kf.world_from_body_vo))
        self._integrate()
        self._promote()
        self._solve(t_raw)

    # --- attitude track ------------------------------------------------------------------------
    def _integrate(self) -> None:
        """Append the pending samples to the attitude track (world-less: relative rotations
        between two track times are exact compositions of the samples between them)."""
        if not self._pending:
            return
        t_new = np.array([s.t_ns for s in self._pending], np.int64)
        g_new = np.array([s.gyro_rad_s for s in self._pending], float).reshape(-1, 3)
        self._pending = []
        if len(self._t):
            keep = t_new > self._t[-1]
            t_new, g_new = t_new[keep], g_new[keep]
        if not len(t_new):
            return
        if not len(self._t):
            t_all, g_all, q = t_new, g_new, np.array([1.0, 0.0, 0.0, 0.0])
            new_q = [q]
        else:
            t_all = np.concatenate([self._t[-1:], t_new])
            g_all = np.vstack([self._gyro[-1:], g_new])
            q, new_q = self._rot[-1], []
        dt = np.diff(t_all) * 1e-9
        steps = _qexp(0.5 * (g_all[1:] + g_all[:-1]) * dt[:, None])
        w, x, y, z = (float(v) for v in q)
        for bw, bx, by, bz in steps.tolist():  # the chain, in plain floats (~1 us a sample)
            w, x, y, z = (
                w * bw - x * bx - y * by - z * bz,
                w * bx + x * bw + y * bz - z * by,
                w * by - x * bz + y * bw + z * bx,
                w * bz + x * by - y * bx + z * bw,
            )
            n = (w * w + x * x + y * y + z * z) ** -0.5
            w, x, y, z = w * n, x * n, y * n, z * n
            new_q.append(np.array([w, x, y, z]))
        self._t = np.concatenate([self._t, t_new])
        self._rot = np.vstack([self._rot, np.asarray(new_q).reshape(-1, 4)])
        self._gyro = np.vstack([self._gyro, g_new])
        # forget what no pair in the window can reach
        if self._pairs or self._waiting:
            oldest = (self._pairs or self._waiting)[0].t0_ns
            cut = int(np.searchsorted(self._t, oldest - int(2 * self.max_s * 1e9))) - 1
            if cut > 0:
                self._t, self._rot, self._gyro = self._t[cut:], self._rot[cut:], self._gyro[cut:]

    def _attitude(self, t_ns: np.ndarray) -> np.ndarray:
        """Track attitude (wxyz) at any times inside it (linearly interpolated gyro)."""
        k = np.clip(np.searchsorted(self._t, t_ns, side="right") - 1, 0, len(self._t) - 2)
        tau = (t_ns - self._t[k]) * 1e-9
        h = (self._t[k + 1] - self._t[k]) * 1e-9
        w0, w1 = self._gyro[k], self._gyro[k + 1]
        w_t = w0 + (w1 - w0) * (tau / h)[:, None]
        return _qmul(self._rot[k], _qexp(0.5 * (w0 + w_t) * tau[:, None]))

    def _promote(self) -> None:
        """Pairs whose gyro is covered over the whole search range join the estimation;
        pairs older than the window leave it."""
        if len(self._t) < 2:
            return
        reach = int((self.max_s + 2 * _H_S) * 1e9)
        while self._waiting and self._waiting[0].t1_ns + reach <= self._t[-1]:
            pair = self._waiting.popleft()
            if pair.t0_ns - reach >= self._t[0]:
                self._pairs.append(pair)
        if self._pairs:
            horizon = self._pairs[-1].t1_ns - int(self.config.time_offset_window_s * 1e9)
            while self._pairs and self._pairs[0].t0_ns < horizon:
                self._pairs.popleft()

    # --- estimation ----------------------------------------------------------------------------
    def _residuals_grid(
        self, t0: np.ndarray, t1: np.ndarray, vis: np.ndarray, d_s: np.ndarray
    ) -> np.ndarray:
        """The residuals at every offset of ``d_s`` (G, M, 3), in one vectorised pass."""
        shift = np.round(np.asarray(d_s) * 1e9).astype(np.int64)[:, None]
        q0 = self._attitude((t0[None, :] + shift).ravel())
        q1 = self._attitude((t1[None, :] + shift).ravel())
        gyro = _qmul(_qconj(q0), q1).reshape(len(shift), len(t0), 4)
        return _qlog(_qmul(_qconj(vis)[None], gyro))

    def _solve(self, t_raw_ns: int) -> None:
        cfg = self.config
        if len(self._pairs) < cfg.time_offset_min_pairs:
            self._record(t_raw_ns)
            return
        pairs = list(self._pairs)
        t0 = np.array([p.t0_ns for p in pairs], np.int64)
        t1 = np.array([p.t1_ns for p in pairs], np.int64)
        vis = np.array([p.vis_wxyz for p in pairs])
        dur = (t1 - t0) * 1e-9
        d = self.offset_s
        if not self._locked or self.updates % 25 == 0:
            found = self._grid(t0, t1, vis, dur)
            if found is None:
                self.status = "beyond the bound"
                self.std_s = float("inf")
                self._record(t_raw_ns)
                self.updates += 1
                return
            d = found
        prior_d = 1.0 / (cfg.time_offset_prior_sigma_ms * 1e-3) ** 2
        b = self.bias_rad_s
        cov = np.full((4, 4), np.inf)
        for _ in range(2):  # warm-started from the last keyframe's estimate
            em, e0, ep = self._residuals_grid(t0, t1, vis, np.array([d - _H_S, d, d + _H_S]))
            jac = (ep - em) / (2 * _H_S)
            r = e0 - dur[:, None] * b
            sigma = max(1.4826 * float(np.median(np.abs(r))), _MIN_NOISE_RAD)
            norm = np.linalg.norm(r, axis=1)
            k = 1.345 * sigma * np.sqrt(3)
            w = np.where(norm <= k, 1.0, k / np.maximum(norm, 1e-300))
            # e(d', b') ~ e0 + J (d' - d) - T b': unknowns x = (d', b')
            a = np.zeros((len(pairs), 3, 4))
            a[:, :, 0] = jac
            a[:, :, 1:] = -dur[:, None, None] * np.eye(3)
            y = jac * d - e0
            hess = np.einsum("m,mij,mik->jk", w, a, a) / sigma**2
            grad = np.einsum("m,mij,mi->j", w, a, y) / sigma**2
            hess[0, 0] += prior_d
            hess[1:, 1:] += np.eye(3) / _BIAS_PRIOR_RAD_S**2
            x = np.linalg.solve(hess, grad)
            d = float(np.clip(x[0], -self.max_s, self.max_s))
            b = x[1:]
            cov = np.linalg.inv(hess)
        self.offset_s, self.bias_rad_s = d, b
        self.std_s = float(np.sqrt(max(cov[0, 0], 0.0)))
        self.updates += 1
        if abs(d) >= self.max_s:
            self.status = "beyond the bound"
        elif self.std_s <= cfg.time_offset_apply_std_ms * 1e-3:
            self.status = "applied"
            self._locked = True
            if cfg.time_offset_online:
                self.applied_ns = int(round(d * 1e9))
        else:
            self.status = "too little motion"
        self._record(t_raw_ns)

    def _grid(
        self, t0: np.ndarray, t1: np.ndarray, vis: np.ndarray, dur: np.ndarray
    ) -> float | None:
        """The grid offset of least robust cost (bias solved per offset), None at the bound."""
        n = int(round(self.max_s / _GRID_S))
        grid = np.arange(-n, n + 1) * _GRID_S
        e = self._residuals_grid(t0, t1, vis, grid)  # (G, M, 3)
        b = (dur[None, :, None] * e).sum(1) / max(float((dur * dur).sum()), 1e-12)  # (G, 3)
        norm = np.linalg.norm(e - dur[None, :, None] * b[:, None, :], axis=2)
        clip = 3 * np.median(norm, axis=1, keepdims=True)
        costs = (np.minimum(norm, clip) ** 2).sum(axis=1)
        i = int(np.argmin(costs))
        if i in (0, len(grid) - 1):
            return None
        return float(grid[i])

    def _record(self, t_raw_ns: int) -> None:
        assert self._t_first_ns is not None
        t_s = (t_raw_ns - self._t_first_ns) * 1e-9
        if self.history and t_s - self.history[-1][0] < 0.5:
            return
        std_ms = self.std_s * 1e3 if np.isfinite(self.std_s) else -1.0
        self.history.append((t_s, self.offset_s * 1e3, std_ms, self.applied_ns * 1e-6))

    @property
    def settled(self) -> bool:
        """Known (applied), or known to be out of reach: nothing more to wait for."""
        return self.status in ("applied", "beyond the bound")

    # --- output --------------------------------------------------------------------------------
    def state(self) -> TimeOffsetState:
        return TimeOffsetState(
            estimate_ns=self.offset_s * 1e9,
            std_ns=self.std_s * 1e9 if np.isfinite(self.std_s) else -1.0,
            applied_ns=self.applied_ns,
            pairs=len(self._pairs),
            status=self.status,
        )

    def summary(self) -> dict[str, object]:
        """The stats.json ``time_offset`` section of the back end."""
        s = self.state()
        return {
            "online": bool(self.config.time_offset_online),
            "estimate_ms": s.estimate_ns * 1e-6,
            "std_ms": s.std_ns * 1e-6 if s.std_ns >= 0 else None,
            "applied_ms": s.applied_ns * 1e-6,
            "status": s.status,
            "pairs": s.pairs,
            "residual_gyro_bias_rad_s": [float(v) for v in self.bias_rad_s],
            "history": [[round(v, 4) for v in h] for h in self.history],
            "history_columns": ["t_s", "estimate_ms", "std_ms", "applied_ms"],
        }

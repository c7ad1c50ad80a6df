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

Hand-written (scipy's ``Rotation`` for exp/log): nothing off the shelf estimates this from a
stream of keyframes.
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


@dataclass(frozen=True)
class _Pair:
    t0_ns: int  # raw (camera) stamps of the two keyframes
    t1_ns: int
    vis: Rotation  # body(t0)_from_body(t1), from the images


class OnlineTimeOffset:
    """Feed it every IMU sample (:meth:`add_imu`) and every keyframe (:meth:`add_keyframe`);
    read :meth:`state`. Synchronous, no threads; owned by ``VioBackend``."""

    def __init__(self, config: BackendConfig) -> None:
        self.config = config
        self.max_s = config.time_offset_max_ms * 1e-3
        self._pending: list[ImuSample] = []
        self._t = np.zeros(0, np.int64)
        self._rot = np.zeros((0, 3, 3))
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
                self._waiting.append(_Pair(last[2], t_raw, Rotation.from_matrix(rel)))
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
            t_all, g_all = t_new, g_new
            rots = [np.eye(3)]
            start = 1
        else:
            t_all = np.concatenate([self._t[-1:], t_new])
            g_all = np.vstack([self._gyro[-1:], g_new])
            rots = [self._rot[-1]]
            start = 1
        dt = np.diff(t_all) * 1e-9
        steps = Rotation.from_rotvec(0.5 * (g_all[1:] + g_all[:-1]) * dt[:, None]).as_matrix()
        r = rots[0]
        out = []
        for step in steps:
            r = r @ step
            out.append(r)
        new_rot = np.asarray(out).reshape(-1, 3, 3)
        self._t = np.concatenate([self._t, t_all[start:]])
        self._rot = np.concatenate([self._rot, new_rot])
        self._gyro = np.vstack([self._gyro, g_all[start:]])
        # forget what no pair in the window can reach
        if self._pairs or self._waiting:
            oldest = (self._pairs or self._waiting)[0].t0_ns
            cut = int(np.searchsorted(self._t, oldest - int(2 * self.max_s * 1e9))) - 1
            if cut > 0:
                self._t, self._rot, self._gyro = self._t[cut:], self._rot[cut:], self._gyro[cut:]

    def _attitude(self, t_ns: np.ndarray) -> Rotation:
        """Track attitude at any times inside it (linearly interpolated gyro)."""
        k = np.clip(np.searchsorted(self._t, t_ns, side="right") - 1, 0, len(self._t) - 2)
        tau = (t_ns - self._t[k]) * 1e-9
        h = (self._t[k + 1] - self._t[k]) * 1e-9
        w0, w1 = self._gyro[k], self._gyro[k + 1]
        w_t = w0 + (w1 - w0) * (tau / h)[:, None]
        part = Rotation.from_rotvec(0.5 * (w0 + w_t) * tau[:, None])
        return Rotation.from_matrix(self._rot[k]) * part

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
    def _residuals(self, t0: np.ndarray, t1: np.ndarray, vis: Rotation, d_s: float) -> np.ndarray:
        shift = int(round(d_s * 1e9))
        gyro = self._attitude(t0 + shift).inv() * self._attitude(t1 + shift)
        return np.asarray((vis.inv() * gyro).as_rotvec())

    def _solve(self, t_raw_ns: int) -> None:
        cfg = self.config
        if len(self._pairs) < cfg.time_offset_min_pairs:
            self._record(t_raw_ns)
            return
        pairs = list(self._pairs)
        t0 = np.array([p.t0_ns for p in pairs], np.int64)
        t1 = np.array([p.t1_ns for p in pairs], np.int64)
        vis = Rotation.concatenate([p.vis for p in pairs])
        dur = (t1 - t0) * 1e-9
        d = self.offset_s
        if not self._locked or self.updates % 10 == 0:
            d = self._grid(t0, t1, vis, dur)
            if d is None:
                self.status = "beyond the bound"
                self.std_s = float("inf")
                self._record(t_raw_ns)
                self.updates += 1
                return
        prior_d = 1.0 / (cfg.time_offset_prior_sigma_ms * 1e-3) ** 2
        b = self.bias_rad_s
        cov = np.full((4, 4), np.inf)
        for _ in range(3):
            e0 = self._residuals(t0, t1, vis, d)
            jac = (self._residuals(t0, t1, vis, d + _H_S) - self._residuals(t0, t1, vis, d - _H_S))
            jac /= 2 * _H_S
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
        self, t0: np.ndarray, t1: np.ndarray, vis: Rotation, dur: np.ndarray
    ) -> float | None:
        """The grid offset of least robust cost (bias solved per offset), None at the bound."""
        n = int(round(self.max_s / _GRID_S))
        grid = np.arange(-n, n + 1) * _GRID_S
        costs = []
        for d in grid:
            e = self._residuals(t0, t1, vis, float(d))
            b = (dur[:, None] * e).sum(0) / max(float((dur * dur).sum()), 1e-12)
            norm = np.linalg.norm(e - dur[:, None] * b, axis=1)
            costs.append(float(np.sum(np.minimum(norm, 3 * np.median(norm)) ** 2)))
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

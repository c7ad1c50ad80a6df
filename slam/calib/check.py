"""Camera-IMU time offset and rotation from a recording, compared with its calibration.

Time offset: the camera's angular rate between consecutive frames (from the images alone,
:mod:`slam.calib.visual_rotation`) against the gyro's, averaged over the same interval shifted by
a candidate offset ``d``; the offset is the ``d`` of highest correlation of the two rate
magnitudes (rotation-invariant, so no extrinsics needed), on a 1 ms grid refined by a parabola
through the peak, with a bootstrap over frame pairs for its spread. Convention as the
calibration's (Kalibr's ``timeshift_cam_imu``): an image stamped ``t`` shows the scene at IMU
time ``t + d``; ``d`` is measured on top of the offset the calibration already applied.

The magnitudes give a coarse offset; with the rotation below, the offset is refined on the
whole rotation vectors (:func:`refine_time_offset`), then the rotation is fitted again.

Rotation (hand-eye): with the offset known, each pair's gyro rotation vector ``a_b`` and visual
rotation vector ``a_c`` satisfy ``a_b = R_bc a_c``; ``R_bc`` (body_from_cam0) is their
least-squares rotation (``scipy.spatial.transform.Rotation.align_vectors``, an SVD fit), with
pairs beyond 3 robust sigmas dropped and a bootstrap for its spread.

What cannot be answered is said, never guessed: too little rotation, rotation about one axis
only, too few trackable frames, a peak at the edge of the search range, a weak correlation:
each raises :class:`CalibrationUnobservable` (a one-line :class:`InputError`).
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from slam.calib.visual_rotation import VisualRotations
from slam.core.calibration import Calibration
from slam.core.errors import InputError

OFFSET_GRID_NS = 1_000_000
MIN_PAIRS = 40
MIN_RATE_STD_RAD_S = 0.1  # the rate must vary this much for a correlation to mean anything
MIN_CORRELATION = 0.8
MIN_SECOND_AXIS = 0.15  # second singular value over the first of the visual rotations
BOOTSTRAP = 200
OFFSET_FLAG_NS = 2_000_000  # residual offsets beyond max(this, 3 sigma) are flagged
ROTATION_FLAG_RAD = np.radians(1.0)  # rotation errors beyond max(this, 3 sigma) are flagged


class CalibrationUnobservable(InputError):
    """The recording cannot answer the question (too little motion, ...): one line, exit 2."""


@dataclass(frozen=True)
class TimeOffsetEstimate:
    """Residual offset (on top of the calibration's), its bootstrap spread, the peak's
    correlation, pairs used, and the search range."""

    offset_ns: float
    std_ns: float
    correlation: float
    pairs: int
    max_offset_ns: int


@dataclass(frozen=True, eq=False)
class RotationEstimate:
    """body_from_cam rotation (3, 3) from the data, its spread (rad), pairs kept."""

    body_from_cam_rot: np.ndarray
    std_rad: float
    pairs: int
    residual_rad: float  # median |a_b - R a_c| of the kept pairs


class GyroIntegral:
    """Exact integral of the linearly interpolated gyro signal: ``rotvec(t0, t1)`` is
    ``int_t0^t1 omega dt`` (rad), the first-order rotation over the interval.

    Why not :func:`slam.imu_buffer.integrate_gyro`: it holds each sample constant until the
    next one, which delays the signal by half a sample (2.5 ms at 200 Hz): that bias is the size
    of what this module measures. Over one frame interval (50 ms) the first-order rotation
    differs from the exact one by far less than the visual rotation's noise."""

    def __init__(self, t_ns: np.ndarray, gyro_rad_s: np.ndarray) -> None:
        self.t0_ns = int(t_ns[0])
        self.t_s = (np.asarray(t_ns, dtype=np.int64) - self.t0_ns) * 1e-9
        self.gyro = np.asarray(gyro_rad_s, dtype=np.float64)
        h = np.diff(self.t_s)[:, None]
        self.cum = np.vstack(
            [np.zeros(3), np.cumsum(0.5 * h * (self.gyro[1:] + self.gyro[:-1]), 0)]
        )

    @property
    def span_ns(self) -> tuple[int, int]:
        return self.t0_ns, self.t0_ns + int(round(self.t_s[-1] * 1e9))

    def at(self, t_ns: np.ndarray) -> np.ndarray:
        """Integral from the first sample to each time (..., 3), times inside the span."""
        t = (np.asarray(t_ns, dtype=np.float64) - self.t0_ns) * 1e-9
        k = np.clip(np.searchsorted(self.t_s, t, side="right") - 1, 0, len(self.t_s) - 2)
        h = self.t_s[k + 1] - self.t_s[k]
        tau = (t - self.t_s[k])[..., None]
        slope = (self.gyro[k + 1] - self.gyro[k]) / h[..., None]
        return self.cum[k] + self.gyro[k] * tau + 0.5 * slope * tau * tau

    def rotvec(self, t0_ns: np.ndarray, t1_ns: np.ndarray) -> np.ndarray:
        return self.at(t1_ns) - self.at(t0_ns)


def _pearson_rows(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Correlation of ``a`` (M,) with every row of ``b`` (K, M)."""
    a0 = a - a.mean()
    b0 = b - b.mean(axis=1, keepdims=True)
    den = np.sqrt((a0 * a0).sum() * (b0 * b0).sum(axis=1))
    return np.asarray((b0 @ a0) / np.maximum(den, 1e-300))


def _peak(curve: np.ndarray) -> tuple[float, int]:
    """Sub-sample position of the maximum (parabola through it and its neighbours)."""
    i = int(np.argmax(curve))
    if 0 < i < len(curve) - 1:
        y0, y1, y2 = curve[i - 1], curve[i], curve[i + 1]
        den = y0 - 2 * y1 + y2
        if den < 0:
            return i + 0.5 * (y0 - y2) / den, i
    return float(i), i


def check_motion(vis: VisualRotations) -> None:
    """CalibrationUnobservable unless the images saw enough, and varied enough, rotation."""
    if len(vis.t0_ns) < MIN_PAIRS:
        raise CalibrationUnobservable(
            f"only {len(vis.t0_ns)} of {vis.pairs_tried} frame pairs could be tracked (need "
            f"{MIN_PAIRS}): record a longer stretch of textured, sharp images"
        )
    rate = vis.rate_rad_s
    if float(rate.std()) < MIN_RATE_STD_RAD_S:
        span_s = (vis.t1_ns[-1] - vis.t0_ns[0]) * 1e-9
        raise CalibrationUnobservable(
            f"too little motion to tell: the camera turned at {np.median(rate):.3f} rad/s "
            f"(median, varying by {rate.std():.3f} rad/s) over {span_s:.1f} s; record 20 s or "
            f"more turning the rig back and forth about all axes (0.5-2 rad/s)"
        )


def estimate_time_offset(
    vis: VisualRotations, gyro: GyroIntegral, max_offset_ns: int = 100_000_000, seed: int = 0
) -> TimeOffsetEstimate:
    """The offset ``d`` (ns) maximising the correlation of the visual and gyro rates."""
    check_motion(vis)
    lo, hi = gyro.span_ns
    keep = (vis.t0_ns - max_offset_ns >= lo) & (vis.t1_ns + max_offset_ns <= hi)
    if keep.sum() < MIN_PAIRS:
        raise CalibrationUnobservable(
            f"the IMU covers only {int(keep.sum())} frame pairs within +-{max_offset_ns * 1e-6:.0f}"
            " ms: the IMU stream must span the images"
        )
    t0, t1 = vis.t0_ns[keep], vis.t1_ns[keep]
    rate_vis = vis.rate_rad_s[keep]
    n_grid = int(max_offset_ns // OFFSET_GRID_NS)
    offsets = np.arange(-n_grid, n_grid + 1) * OFFSET_GRID_NS
    dt_s = ((t1 - t0) * 1e-9)[None, :]
    rate_gyro = (
        np.linalg.norm(
            gyro.rotvec(t0[None, :] + offsets[:, None], t1[None, :] + offsets[:, None]), axis=2
        )
        / dt_s
    )
    curve = _pearson_rows(rate_vis, rate_gyro)
    pos, i = _peak(curve)
    if i in (0, len(offsets) - 1):
        raise CalibrationUnobservable(
            f"the best time offset lies at the edge of the search range "
            f"({offsets[i] * 1e-6:+.0f} ms): the offset is larger; widen --max-offset or "
            f"check that camera and IMU stamps come from one clock"
        )
    if curve[i] < MIN_CORRELATION:
        raise CalibrationUnobservable(
            f"no clear time offset: the gyro and visual rates correlate at {curve[i]:.2f} at "
            f"best (need {MIN_CORRELATION}); record faster, varied rotation with sharp images"
        )
    rng = np.random.default_rng(seed)
    m = len(rate_vis)
    boot = []
    for _ in range(BOOTSTRAP):
        idx = rng.integers(0, m, m)
        boot.append(_peak(_pearson_rows(rate_vis[idx], rate_gyro[:, idx]))[0])
    to_ns = OFFSET_GRID_NS
    return TimeOffsetEstimate(
        offset_ns=float(offsets[0] + pos * to_ns),
        std_ns=float(np.std(boot) * to_ns),
        correlation=float(curve[i]),
        pairs=m,
        max_offset_ns=int(max_offset_ns),
    )


def refine_time_offset(
    vis: VisualRotations,
    gyro: GyroIntegral,
    coarse: TimeOffsetEstimate,
    body_from_cam_rot: np.ndarray,
    half_window_ns: int = 20_000_000,
    seed: int = 0,
) -> TimeOffsetEstimate:
    """Refine the offset with the whole rotation vectors: ``d`` minimising the sum of
    ``|a_b(d) - R_bc a_c|^2`` over the pairs (those within 3 robust sigmas at the coarse
    offset), near the coarse estimate. The rate magnitudes alone are biased by the visual
    rotations' errors (an essential matrix trades some rotation for translation, and that error
    follows the motion); three components with the rotation known are not (measured: 13.9 ->
    15.0 ms for 15 ms injected, on the `aggressive` profile)."""
    lo, hi = gyro.span_ns
    centre = int(round(coarse.offset_ns / OFFSET_GRID_NS)) * OFFSET_GRID_NS
    n = half_window_ns // OFFSET_GRID_NS
    offsets = centre + np.arange(-n, n + 1) * OFFSET_GRID_NS
    keep = (vis.t0_ns + offsets[0] >= lo) & (vis.t1_ns + offsets[-1] <= hi)
    a_cam = vis.rotvec_cam_rad[keep] @ body_from_cam_rot.T
    t0, t1 = vis.t0_ns[keep], vis.t1_ns[keep]
    a_body = gyro.rotvec(t0[None, :] + offsets[:, None], t1[None, :] + offsets[:, None])
    sq = ((a_body - a_cam[None]) ** 2).sum(axis=2)  # (K, M)
    at_centre = np.sqrt(sq[n])
    inl = at_centre < 3 * (1.4826 * float(np.median(at_centre)) + 1e-12)
    sq = sq[:, inl]
    pos, i = _peak(-sq.sum(axis=1))
    if i in (0, len(offsets) - 1):
        return coarse  # no minimum near the coarse peak: keep the correlation's answer
    rng = np.random.default_rng(seed)
    m = sq.shape[1]
    boot = [_peak(-sq[:, rng.integers(0, m, m)].sum(axis=1))[0] for _ in range(BOOTSTRAP)]
    return TimeOffsetEstimate(
        offset_ns=float(offsets[0] + pos * OFFSET_GRID_NS),
        std_ns=float(np.std(boot) * OFFSET_GRID_NS),
        correlation=coarse.correlation,
        pairs=m,
        max_offset_ns=coarse.max_offset_ns,
    )


def _fit_rotation(a_body: np.ndarray, a_cam: np.ndarray) -> np.ndarray:
    rot, _ = Rotation.align_vectors(a_body, a_cam)
    return np.asarray(rot.as_matrix())


def estimate_camera_rotation(
    vis: VisualRotations, gyro: GyroIntegral, offset_ns: float, seed: int = 0
) -> RotationEstimate:
    """body_from_cam rotation from the pairs' rotation vectors (gyro ones at the offset)."""
    check_motion(vis)
    lo, hi = gyro.span_ns
    shift = int(round(offset_ns))
    keep = (vis.t0_ns + shift >= lo) & (vis.t1_ns + shift <= hi)
    a_cam = vis.rotvec_cam_rad[keep]
    a_body = gyro.rotvec(vis.t0_ns[keep] + shift, vis.t1_ns[keep] + shift)
    sv = np.linalg.svd(a_cam, compute_uv=False)
    if len(sv) < 3 or sv[1] < MIN_SECOND_AXIS * sv[0]:
        raise CalibrationUnobservable(
            "the rig turned about one axis only: the camera-IMU rotation is not observable; "
            "record rotation about at least two axes"
        )
    rot = _fit_rotation(a_body, a_cam)
    for _ in range(3):
        resid = np.linalg.norm(a_body - a_cam @ rot.T, axis=1)
        sigma = 1.4826 * float(np.median(resid)) + 1e-9
        inl = resid < 3 * sigma
        rot = _fit_rotation(a_body[inl], a_cam[inl])
    resid = np.linalg.norm(a_body - a_cam @ rot.T, axis=1)
    inl = resid < 3 * (1.4826 * float(np.median(resid)) + 1e-9)
    rng = np.random.default_rng(seed)
    ab, ac = a_body[inl], a_cam[inl]
    angles = []
    for _ in range(BOOTSTRAP):
        idx = rng.integers(0, len(ab), len(ab))
        angles.append(Rotation.from_matrix(_fit_rotation(ab[idx], ac[idx]) @ rot.T).as_rotvec())
    spread = float(np.sqrt((np.asarray(angles) ** 2).sum(axis=1).mean()))
    return RotationEstimate(
        body_from_cam_rot=rot,
        std_rad=spread,
        pairs=int(inl.sum()),
        residual_rad=float(np.median(resid[inl])),
    )


@dataclass(frozen=True, eq=False)
class CalibCheck:
    """What `slam calib check` found, and whether the calibration agrees."""

    time_offset: TimeOffsetEstimate
    rotation: RotationEstimate
    given_offset_ns: int
    given_body_from_cam_rot: np.ndarray
    duration_s: float

    @property
    def rotation_error_rad(self) -> float:
        """Angle between the estimated and the given camera-IMU rotations."""
        d = self.rotation.body_from_cam_rot @ self.given_body_from_cam_rot.T
        return float(np.linalg.norm(Rotation.from_matrix(d).as_rotvec()))

    @property
    def correction_rotvec_rad(self) -> np.ndarray:
        """body_from_cam_est = exp(correction) @ body_from_cam_given (body frame)."""
        d = self.rotation.body_from_cam_rot @ self.given_body_from_cam_rot.T
        return np.asarray(Rotation.from_matrix(d).as_rotvec())

    @property
    def offset_flagged(self) -> bool:
        t = self.time_offset
        return abs(t.offset_ns) > max(OFFSET_FLAG_NS, 3 * t.std_ns)

    @property
    def rotation_flagged(self) -> bool:
        return self.rotation_error_rad > max(ROTATION_FLAG_RAD, 3 * self.rotation.std_rad)

    @property
    def ok(self) -> bool:
        return not (self.offset_flagged or self.rotation_flagged)

    def report(self) -> list[str]:
        """The verdict, one finding a line, with what to do."""
        t = self.time_offset
        total_ms = (self.given_offset_ns + t.offset_ns) * 1e-6
        given_ms = self.given_offset_ns * 1e-6
        lines = [
            f"from {self.duration_s:.1f} s: {t.pairs} frame pairs (gyro-visual rate "
            f"correlation {t.correlation:.3f}), {self.rotation.pairs} for the rotation"
        ]
        head = (
            f"time offset {t.offset_ns * 1e-6:+.1f} ms +- {t.std_ns * 1e-6:.1f} ms on top of the "
            f"calibration's {given_ms:+.1f} ms"
        )
        if self.offset_flagged:
            lines.append(
                f"{head}: WRONG. Images show the scene {abs(t.offset_ns) * 1e-6:.1f} ms "
                f"{'later' if t.offset_ns > 0 else 'earlier'} (in IMU time) than the "
                f"calibration says: fix the camera driver's stamps, or set the time offset to "
                f"{total_ms:+.1f} ms (Kalibr camchain timeshift_cam_imu: {total_ms * 1e-3:.4f}, "
                f"passed with --camchain)"
            )
        else:
            lines.append(f"{head}: OK")
        err_deg = np.degrees(self.rotation_error_rad)
        std_deg = np.degrees(self.rotation.std_rad)
        head = f"camera-IMU rotation {err_deg:.2f} deg +- {std_deg:.2f} deg from the calibration's"
        if self.rotation_flagged:
            rv = np.degrees(self.correction_rotvec_rad)
            lines.append(
                f"{head}: WRONG. Re-calibrate (Kalibr), or rotate body_from_cam by the rotation "
                f"vector ({rv[0]:+.2f}, {rv[1]:+.2f}, {rv[2]:+.2f}) deg in the body frame"
            )
        else:
            lines.append(f"{head}: OK")
        return lines

    def to_dict(self) -> dict[str, object]:
        t, r = self.time_offset, self.rotation
        return {
            "ok": bool(self.ok),
            "duration_s": self.duration_s,
            "time_offset": {
                "residual_ms": t.offset_ns * 1e-6,
                "std_ms": t.std_ns * 1e-6,
                "calibration_ms": self.given_offset_ns * 1e-6,
                "total_ms": (self.given_offset_ns + t.offset_ns) * 1e-6,
                "correlation": t.correlation,
                "pairs": t.pairs,
                "max_offset_ms": t.max_offset_ns * 1e-6,
                "flagged": bool(self.offset_flagged),
            },
            "rotation": {
                "error_deg": float(np.degrees(self.rotation_error_rad)),
                "std_deg": float(np.degrees(r.std_rad)),
                "correction_rotvec_deg": np.degrees(self.correction_rotvec_rad).tolist(),
                "body_from_cam0_rot": r.body_from_cam_rot.tolist(),
                "pairs": r.pairs,
                "residual_deg": float(np.degrees(r.residual_rad)),
                "flagged": bool(self.rotation_flagged),
            },
        }


def check_calibration(
    frames: Iterable[tuple[int, np.ndarray]],
    imu_t_ns: np.ndarray,
    imu_gyro_rad_s: np.ndarray,
    calibration: Calibration,
    max_offset_ns: int = 100_000_000,
) -> CalibCheck:
    """Estimate offset and rotation from cam0's (t_ns, image) frames (stamps in the IMU clock,
    the calibration's offset applied) and the gyro, and compare them with ``calibration``."""
    from slam.calib.visual_rotation import visual_rotations

    if len(imu_t_ns) < 2:
        raise InputError("the recording has no IMU stream: nothing to check the cameras against")
    vis = visual_rotations(frames, calibration.cam0.intrinsics)
    gyro = GyroIntegral(imu_t_ns, imu_gyro_rad_s)
    coarse = estimate_time_offset(vis, gyro, max_offset_ns)
    rotation = estimate_camera_rotation(vis, gyro, coarse.offset_ns)
    offset = refine_time_offset(vis, gyro, coarse, rotation.body_from_cam_rot)
    rotation = estimate_camera_rotation(vis, gyro, offset.offset_ns)
    return CalibCheck(
        time_offset=offset,
        rotation=rotation,
        given_offset_ns=int(calibration.time_offset_ns),
        given_body_from_cam_rot=np.asarray(calibration.cam0.body_from_cam)[:3, :3],
        duration_s=float((vis.t1_ns[-1] - vis.t0_ns[0]) * 1e-9),
    )

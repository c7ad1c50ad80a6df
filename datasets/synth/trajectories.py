"""Smooth motions with analytic derivatives: named profiles and spline-fitted trajectory files.

A motion gives, at any times, world_from_body (rotation + position), the world velocity and
acceleration, and the body angular velocity, all consistent (derivatives are analytic, not
numeric), so the IMU simulator can produce exact measurements.

Profiles are sums of sinusoids of a *phase* ``s`` (seconds): position ``x, y, z`` and the
orientation as yaw/pitch/roll (``Rz(yaw) Ry(pitch) Rx(roll)``) of a nominal frame (x forward,
y left, z up) to which the body is attached like the EuRoC IMU: body x up, body z forward, so
the EuRoC-like cameras (z along body z) look forward. A still start is a C3 time warp
``s(t)``: s = 0 for ``t < still_s``, then a quintic ramp of the phase rate from 0 to 1.

Body = IMU frame. World z is up, gravity is (0, 0, -g).
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from scipy.interpolate import CubicSpline
from scipy.spatial.transform import Rotation, RotationSpline

from datasets.euroc import read_trajectory_file
from slam.core.errors import InputError

# columns: body x (up), body y (right), body z (forward) in the nominal frame (x fwd, y left, z up)
NOMINAL_FROM_BODY = np.array([[0.0, 0.0, 1.0], [0.0, -1.0, 0.0], [1.0, 0.0, 0.0]])


@dataclass(frozen=True, eq=False)
class MotionSamples:
    """Motion state at times ``t_s`` (N,): world-frame kinematics and body angular velocity."""

    t_s: np.ndarray
    positions_m: np.ndarray  # (N, 3) world
    velocities_m_s: np.ndarray  # (N, 3) world
    accelerations_m_s2: np.ndarray  # (N, 3) world
    world_from_body_rot: np.ndarray  # (N, 3, 3)
    omega_body_rad_s: np.ndarray  # (N, 3) angular velocity in the body frame

    def world_from_body(self) -> np.ndarray:
        """(N, 4, 4) poses."""
        n = len(self.t_s)
        out = np.zeros((n, 4, 4))
        out[:, :3, :3] = self.world_from_body_rot
        out[:, :3, 3] = self.positions_m
        out[:, 3, 3] = 1.0
        return out


class Motion(ABC):
    """A smooth body motion over ``[t_start_s, t_end_s]``."""

    t_start_s: float = 0.0
    t_end_s: float = float("inf")

    @abstractmethod
    def sample(self, t_s: np.ndarray) -> MotionSamples:
        """State at the given times (seconds)."""


@dataclass(frozen=True)
class SinusoidChannel:
    """``c0 + c1 s + sum_k a_k sin(w_k s + phi_k)`` with exact derivatives in s."""

    c0: float = 0.0
    c1: float = 0.0
    terms: tuple[tuple[float, float, float], ...] = ()  # (amplitude, rad/s, phase rad)

    def eval(self, s: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Value, first and second derivative with respect to s."""
        v = self.c0 + self.c1 * s
        d1 = np.full_like(s, self.c1)
        d2 = np.zeros_like(s)
        for a, w, phi in self.terms:
            arg = w * s + phi
            sn, cs = np.sin(arg), np.cos(arg)
            v = v + a * sn
            d1 = d1 + a * w * cs
            d2 = d2 - a * w * w * sn
        return v, d1, d2


@dataclass(frozen=True)
class TimeWarp:
    """Phase ``s(t)``: still until ``still_s``, then a quintic ramp of ds/dt from 0 to 1 over
    ``ramp_s`` (s, ds/dt and d2s/dt2 continuous). ``still_s = ramp_s = 0``: s = t."""

    still_s: float = 2.0
    ramp_s: float = 2.0

    def eval(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        t = np.asarray(t, dtype=float)
        if self.ramp_s <= 0:
            s = np.maximum(t - self.still_s, 0.0)
            return s, (t >= self.still_s).astype(float), np.zeros_like(t)
        x = np.clip((t - self.still_s) / self.ramp_s, 0.0, 1.0)
        s_ramp = self.ramp_s * (x**6 - 3 * x**5 + 2.5 * x**4)
        sd_ramp = 10 * x**3 - 15 * x**4 + 6 * x**5
        sdd_ramp = (30 * x**2 - 60 * x**3 + 30 * x**4) / self.ramp_s
        after = t >= self.still_s + self.ramp_s
        s = np.where(after, 0.5 * self.ramp_s + (t - self.still_s - self.ramp_s), s_ramp)
        sd = np.where(after, 1.0, sd_ramp)
        sdd = np.where(after, 0.0, sdd_ramp)
        return s, sd, sdd


def _rz(a: np.ndarray) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    z, o = np.zeros_like(a), np.ones_like(a)
    return np.stack(
        [np.stack([c, -s, z], -1), np.stack([s, c, z], -1), np.stack([z, z, o], -1)], -2
    )


def _ry(a: np.ndarray) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    z, o = np.zeros_like(a), np.ones_like(a)
    return np.stack(
        [np.stack([c, z, s], -1), np.stack([z, o, z], -1), np.stack([-s, z, c], -1)], -2
    )


def _rx(a: np.ndarray) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    z, o = np.zeros_like(a), np.ones_like(a)
    return np.stack(
        [np.stack([o, z, z], -1), np.stack([z, c, -s], -1), np.stack([z, s, c], -1)], -2
    )


@dataclass(frozen=True)
class ProfileMotion(Motion):
    """Position and yaw/pitch/roll as sinusoid channels of a time-warped phase."""

    name: str
    x: SinusoidChannel
    y: SinusoidChannel
    z: SinusoidChannel
    yaw: SinusoidChannel
    pitch: SinusoidChannel
    roll: SinusoidChannel
    warp: TimeWarp = field(default_factory=TimeWarp)
    kind: str = "room"  # which scene the profile is made for: "room" or "hall"
    default_duration_s: float = 40.0
    t_start_s: float = 0.0
    t_end_s: float = float("inf")

    def sample(self, t_s: np.ndarray) -> MotionSamples:
        t = np.atleast_1d(np.asarray(t_s, dtype=float))
        s, sd, sdd = self.warp.eval(t)
        pos, vel, acc = [], [], []
        for ch in (self.x, self.y, self.z):
            v, d1, d2 = ch.eval(s)
            pos.append(v)
            vel.append(d1 * sd)
            acc.append(d2 * sd * sd + d1 * sdd)
        (yaw, dyaw, _), (pitch, dpitch, _), (roll, droll, _) = (
            self.yaw.eval(s),
            self.pitch.eval(s),
            self.roll.eval(s),
        )
        rz, ry, rx = _rz(yaw), _ry(pitch), _rx(roll)
        rzy = rz @ ry
        rot = rzy @ rx @ NOMINAL_FROM_BODY
        # world angular velocity of a ZYX Euler chain: yaw' ez + pitch' Rz ey + roll' Rz Ry ex
        omega_w = (
            (dyaw * sd)[:, None] * np.array([0.0, 0.0, 1.0])
            + (dpitch * sd)[:, None] * rz[:, :, 1]
            + (droll * sd)[:, None] * rzy[:, :, 0]
        )
        omega_b = np.einsum("nji,nj->ni", rot, omega_w)
        return MotionSamples(
            t_s=t,
            positions_m=np.stack(pos, 1),
            velocities_m_s=np.stack(vel, 1),
            accelerations_m_s2=np.stack(acc, 1),
            world_from_body_rot=rot,
            omega_body_rad_s=omega_b,
        )


def _sin(*terms: tuple[float, float, float], c0: float = 0.0, c1: float = 0.0) -> SinusoidChannel:
    return SinusoidChannel(c0=c0, c1=c1, terms=tuple(terms))


PROFILES = ("figure8", "loop", "aggressive", "hall")


def make_profile(name: str, moving_start: bool = False) -> ProfileMotion:
    """A named motion profile.

    - ``figure8``: slow figure-8 in the 8x6x3 m room (24 s per figure, <= 0.8 m/s), looking
      around +x with +-1 rad of yaw.
    - ``loop``: an ellipse (2.3 x 1.4 m) looking outwards, yaw +2 pi per lap, with small
      0.3-0.5 Hz wobbles; it revisits its start pose exactly after 75 s of motion (t = 78 s
      with the still start).
    - ``aggressive``: a fast figure-8 (7 s period, <= 2.5 m/s, 4 m/s^2, 3 rad/s) with shakes.
    - ``hall``: an 11 x 3 m ellipse in the 30x10x3 m hall, one lap per 60 s (~48 m per lap),
      looking forward-outward, with small wobbles; 140 s default ~ 117 m of path.

    ``moving_start``: no still start (the phase runs from t = 0); default: still for 2 s,
    then a 2 s smooth ramp to full speed.
    """
    warp = TimeWarp(0.0, 0.0) if moving_start else TimeWarp(2.0, 2.0)
    two_pi = 2.0 * np.pi
    if name == "figure8":
        w = two_pi / 24.0
        return ProfileMotion(
            name=name,
            x=_sin((2.0, w, 0.0)),
            y=_sin((1.1, 2 * w, 0.0)),
            z=_sin((0.25, w, 0.7), c0=1.5),
            yaw=_sin((0.9, w, 0.3), (0.25, 2 * w, 0.0)),
            pitch=_sin((0.08, 3 * w, 0.0), c0=0.12),
            roll=_sin((0.06, 2 * w, 1.0)),
            warp=warp,
            default_duration_s=40.0,
        )
    if name == "loop":
        w = two_pi / 75.0
        return ProfileMotion(
            name=name,
            # slow lap + ~0.3-0.5 Hz wobbles (integer harmonics: the lap stays periodic) that
            # excite the IMU like a hand-held / MAV sequence (~1.5 m/s^2, ~0.4 rad/s)
            x=_sin((2.3, w, np.pi / 2), (0.12, 6 * w, 0.0), (0.12, 4 * w, 0.0), (0.1, 30 * w, 0.0)),
            y=_sin((1.4, w, 0.0), (0.1, 5 * w, 0.4), (0.1, 23 * w, 0.5)),
            z=_sin((0.2, 2 * w, 0.0), (0.07, 37 * w, 0.0), c0=1.4),
            yaw=_sin((0.2, 3 * w, 0.0), (0.1, 7 * w, 1.0), (0.08, 19 * w, 0.0), c1=w),
            pitch=_sin((0.06, 5 * w, 0.0), (0.05, 29 * w, 0.3), c0=0.1),
            roll=_sin((0.05, 3 * w, 0.5), (0.05, 31 * w, 0.0)),
            warp=warp,
            default_duration_s=80.0,
        )
    if name == "aggressive":
        w = two_pi / 7.0
        return ProfileMotion(
            name=name,
            x=_sin((1.8, w, 0.0)),
            y=_sin((1.0, 2 * w, 0.0)),
            z=_sin((0.3, 3 * w, 0.4), c0=1.5),
            yaw=_sin((0.8, w, 0.0), (0.35, 3 * w, 0.5), (0.1, two_pi * 1.7, 0.0)),
            pitch=_sin((0.25, 2 * w, 1.1), (0.05, two_pi * 2.3, 0.0), c0=0.1),
            roll=_sin((0.3, 1.5 * w, 0.0), (0.05, two_pi * 1.9, 0.3)),
            warp=warp if moving_start else TimeWarp(2.0, 1.5),
            default_duration_s=30.0,
        )
    if name == "hall":
        w = two_pi / 60.0
        return ProfileMotion(
            name=name,
            x=_sin((11.0, w, np.pi / 2)),
            y=_sin((3.0, w, 0.0), (0.3, 3 * w, 0.0), (0.1, 25 * w, 0.0)),
            z=_sin((0.3, 2 * w, 0.0), (0.08, 31 * w, 0.4), c0=1.5),
            yaw=_sin((0.15, 4 * w, 0.0), (0.06, 21 * w, 0.0), c0=np.pi / 2 - 0.6, c1=w),
            pitch=_sin((0.05, 3 * w, 0.0), (0.04, 27 * w, 0.0), c0=0.08),
            roll=_sin((0.04, 5 * w, 0.0), (0.04, 33 * w, 0.7)),
            warp=warp,
            kind="hall",
            default_duration_s=140.0,
        )
    raise InputError(f"unknown trajectory profile {name!r}; choose one of {', '.join(PROFILES)}")


# ------------------------------------------------------------------------------------------
# trajectories read from files


@dataclass(frozen=True, eq=False)
class SplineMotion(Motion):
    """A motion interpolating timestamped poses: cubic spline positions (C2), scipy
    ``RotationSpline`` orientations; derivatives from the splines."""

    t0_ns: int
    t_rel_s: np.ndarray
    positions_m: np.ndarray
    q_wxyz: np.ndarray
    name: str = "file"

    def __post_init__(self) -> None:
        object.__setattr__(self, "t_start_s", float(self.t_rel_s[0]))
        object.__setattr__(self, "t_end_s", float(self.t_rel_s[-1]))
        object.__setattr__(self, "_pos", CubicSpline(self.t_rel_s, self.positions_m, axis=0))
        rot = Rotation.from_quat(self.q_wxyz[:, [1, 2, 3, 0]])  # scipy wants x,y,z,w
        object.__setattr__(self, "_rot", RotationSpline(self.t_rel_s, rot))

    def sample(self, t_s: np.ndarray) -> MotionSamples:
        t = np.clip(np.atleast_1d(np.asarray(t_s, dtype=float)), self.t_start_s, self.t_end_s)
        pos_spline: CubicSpline = self._pos  # type: ignore[attr-defined]
        rot_spline: RotationSpline = self._rot  # type: ignore[attr-defined]
        rot = rot_spline(t).as_matrix()
        # RotationSpline's first derivative is the angular rate in the rotated (body) frame
        # (checked against finite differences of R^T dR/dt)
        omega_b = np.atleast_2d(rot_spline(t, 1))
        return MotionSamples(
            t_s=t,
            positions_m=pos_spline(t),
            velocities_m_s=pos_spline(t, 1),
            accelerations_m_s2=pos_spline(t, 2),
            world_from_body_rot=rot,
            omega_body_rad_s=omega_b,
        )


def motion_from_file(path: str | Path) -> SplineMotion:
    """A spline motion through the poses of a TUM or EuRoC ground-truth file.

    Times are relative to the file's first pose (``t0_ns`` keeps the offset)."""
    traj = read_trajectory_file(path)
    if len(traj) < 4:
        raise InputError(f"{path}: need at least 4 poses with distinct times")
    t_ns, pos, q_wxyz = traj.t_ns, traj.positions_m, traj.q_wxyz
    t_rel_s = (t_ns - t_ns[0]).astype(np.float64) * 1e-9
    return SplineMotion(
        t0_ns=int(t_ns[0]), t_rel_s=t_rel_s, positions_m=pos, q_wxyz=q_wxyz, name=Path(path).stem
    )

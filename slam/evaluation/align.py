"""Align an estimate to the reference before computing errors.

Methods (``ALIGNMENTS``), each estimating ``ref_from_est`` (a similarity ``s``, ``R``, ``t``)
from associated positions, optionally the first N pairs only:
  se3     Umeyama, rotation + translation (evo ``-a``)
  sim3    Umeyama with scale (evo ``-as``), for monocular estimates
  scale   scale only (evo ``-s``)
  posyaw  4-DoF: translation + rotation about gravity (z); what VIO can observe
  origin  the first estimate pose put on the first reference pose (evo ``--align_origin``)
  none    identity
The estimate's poses become ``T_est' = [R | t] * [R_est | s t_est]``, as evo applies them.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from slam.core.errors import InputError
from slam.evaluation import lie

ALIGNMENTS = ("se3", "sim3", "scale", "posyaw", "origin", "none")


@dataclass(frozen=True)
class Alignment:
    """The transform applied to the estimate: p_ref = scale * rotation @ p_est + translation_m."""

    method: str
    rotation: np.ndarray
    translation_m: np.ndarray
    scale: float
    n_used: int

    def describe(self) -> str:
        """One line for the console: method, poses used, scale, rotation angle, translation
        (only what the method estimates; ``none`` says that the estimate is used as given)."""
        if self.method == "none":
            return "no alignment (--align none): the estimate is compared as given, scale 1"
        used = f"alignment {self.method} on {self.n_used} pose{'s' if self.n_used != 1 else ''}"
        if self.method == "scale":
            return f"{used}: scale {self.scale:.6f}"
        angle_deg = float(np.degrees(lie.rotation_angles_rad(self.rotation[None])[0]))
        t = ", ".join(f"{v:.4f}" for v in self.translation_m)
        return f"{used}: scale {self.scale:.6f}, rotation {angle_deg:.4f} deg, translation [{t}] m"

    def sim3(self) -> np.ndarray:
        """The 4x4 similarity ref_from_est (rotation scaled)."""
        m = np.eye(4)
        m[:3, :3] = self.scale * self.rotation
        m[:3, 3] = self.translation_m
        return m


def umeyama(x: np.ndarray, y: np.ndarray, with_scale: bool) -> tuple[np.ndarray, np.ndarray, float]:
    """R, t, c minimising ||y - (c R x + t)||^2 for (N, 3) point sets (Umeyama 1991, as evo)."""
    n = len(x)
    mean_x, mean_y = x.mean(axis=0), y.mean(axis=0)
    xc, yc = x - mean_x, y - mean_y
    sigma_x = 1.0 / n * (np.linalg.norm(xc) ** 2)
    cov_xy = np.multiply(1.0 / n, yc.T @ xc)
    u, d, v = np.linalg.svd(cov_xy)
    if np.count_nonzero(d > np.finfo(d.dtype).eps) < 2:
        raise InputError(
            "degenerate alignment: the associated positions are (nearly) collinear or one "
            "point; use --align origin or none, or more poses"
        )
    s = np.eye(3)
    if np.linalg.det(u) * np.linalg.det(v) < 0.0:
        s[2, 2] = -1.0
    r = u @ s @ v
    c = 1.0 / sigma_x * np.trace(np.diag(d) @ s) if with_scale else 1.0
    t = mean_y - np.multiply(c, r @ mean_x)
    return r, t, float(c)


def ate_se3_rmse_m(est_positions_m: np.ndarray, ref_positions_m: np.ndarray) -> float:
    """Position RMSE (m) after the SE(3) Umeyama alignment of the estimate to the reference:
    the ATE of (N, 3) positions already associated (tests, benchmarks)."""
    rot, trans, _ = umeyama(est_positions_m, ref_positions_m, False)
    err = est_positions_m @ rot.T + trans - ref_positions_m
    return float(np.sqrt(np.mean(np.sum(err**2, axis=1))))


def posyaw(x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Yaw rotation R_z and t minimising ||y - (R_z x + t)||^2 (closed form)."""
    xc, yc = x - x.mean(axis=0), y - y.mean(axis=0)
    sin_sum = float(np.sum(xc[:, 0] * yc[:, 1] - xc[:, 1] * yc[:, 0]))
    cos_sum = float(np.sum(xc[:, 0] * yc[:, 0] + xc[:, 1] * yc[:, 1]))
    r = lie.yaw_rotation(np.arctan2(sin_sum, cos_sum))
    t = y.mean(axis=0) - r @ x.mean(axis=0)
    return r, t


def estimate_alignment(
    ref_poses: np.ndarray, est_poses: np.ndarray, method: str, n_first: int | None = None
) -> Alignment:
    """The alignment ``method`` from associated (N, 4, 4) poses, on the first ``n_first`` if given."""
    if method not in ALIGNMENTS:
        raise InputError(f"unknown alignment {method!r}; choose one of {', '.join(ALIGNMENTS)}")
    n = len(ref_poses) if n_first in (None, -1) else int(n_first)
    if n < 1:
        raise InputError(f"--align-first must be at least 1 (got {n})")
    n = min(n, len(ref_poses))
    x = est_poses[:n, :3, 3]
    y = ref_poses[:n, :3, 3]
    eye, zero = np.eye(3), np.zeros(3)
    if method == "none":
        return Alignment(method, eye, zero, 1.0, 0)
    if method == "origin":
        m = ref_poses[0] @ lie.inverse(est_poses[:1])[0]
        return Alignment(method, m[:3, :3], m[:3, 3], 1.0, 1)
    if n < 3 and method in ("se3", "sim3", "scale"):
        raise InputError(f"{method} alignment needs at least 3 pose pairs (have {n})")
    if method == "posyaw":
        if n < 2:
            raise InputError("posyaw alignment needs at least 2 pose pairs")
        r, t = posyaw(x, y)
        return Alignment(method, r, t, 1.0, n)
    r, t, c = umeyama(x, y, with_scale=method in ("sim3", "scale"))
    if method == "scale":
        return Alignment(method, eye, zero, c, n)
    return Alignment(method, r, t, c, n)


def apply_alignment(est_poses: np.ndarray, alignment: Alignment) -> np.ndarray:
    """est poses (N, 4, 4) -> aligned copy: rotation R R_est, position R (s p) + t."""
    out = np.array(est_poses, copy=True)
    if alignment.method == "none":
        return out
    r = alignment.rotation
    out[:, :3, :3] = r @ est_poses[:, :3, :3]
    out[:, :3, 3] = (alignment.scale * est_poses[:, :3, 3]) @ r.T + alignment.translation_m
    return out

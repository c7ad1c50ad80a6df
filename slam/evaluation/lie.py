"""Batched SE(3)/SO(3) helpers in plain numpy (no scipy import: it costs ~0.3 s of start-up).

The conversions reproduce the numerics of the reference tools on purpose:
``quat_wxyz_to_matrices`` follows evo's ``transformations.quaternion_matrix`` (it rescales a
non-unit quaternion by sqrt(2/n)) and ``rotation_angles_rad`` follows scipy's
``Rotation.from_matrix(...).magnitude()`` (SVD orthogonalisation of non-orthogonal input, then
the largest-diagonal quaternion extraction, then ``2 atan2(|v|, |w|)``), so angles agree with
evo to the last few ulps instead of the ~1e-8 rad an arccos formula loses near zero.
"""

from __future__ import annotations

import numpy as np


def quat_wxyz_to_matrices(q_wxyz: np.ndarray) -> np.ndarray:
    """(N, 4) w,x,y,z (any norm > 0) -> (N, 3, 3) rotation matrices."""
    q = np.asarray(q_wxyz, dtype=np.float64)
    n = np.einsum("ij,ij->i", q, q)
    q = q * np.sqrt(2.0 / n)[:, None]
    w, x, y, z = q[:, 0], q[:, 1], q[:, 2], q[:, 3]
    r = np.empty((len(q), 3, 3))
    r[:, 0, 0] = 1.0 - y * y - z * z
    r[:, 0, 1] = x * y - z * w
    r[:, 0, 2] = x * z + y * w
    r[:, 1, 0] = x * y + z * w
    r[:, 1, 1] = 1.0 - x * x - z * z
    r[:, 1, 2] = y * z - x * w
    r[:, 2, 0] = x * z - y * w
    r[:, 2, 1] = y * z + x * w
    r[:, 2, 2] = 1.0 - x * x - y * y
    return r


def poses_from_pq(positions_m: np.ndarray, q_wxyz: np.ndarray) -> np.ndarray:
    """(N, 3) positions + (N, 4) q_wxyz -> (N, 4, 4) world_from_body."""
    n = len(positions_m)
    out = np.zeros((n, 4, 4))
    out[:, :3, :3] = quat_wxyz_to_matrices(q_wxyz)
    out[:, :3, 3] = positions_m
    out[:, 3, 3] = 1.0
    return out


def orthogonalise(rotations: np.ndarray) -> np.ndarray:
    """Replace matrices that are not orthogonal to 1e-12 by their nearest rotation (U V^T), as scipy."""
    r = np.array(rotations, dtype=np.float64, copy=True)
    gram = r @ np.swapaxes(r, -1, -2)
    ok = np.all(np.isclose(gram, np.eye(3), rtol=1e-5, atol=1e-12), axis=(-2, -1))
    if not np.all(ok):
        u, _, vt = np.linalg.svd(r[~ok], full_matrices=False)
        r[~ok] = u @ vt
    return r


def matrices_to_quat_xyzw_raw(rotations: np.ndarray) -> np.ndarray:
    """Unnormalised quaternion (x, y, z, w) of orthogonal matrices; scipy's branch choice."""
    m = rotations
    trace = m[:, 0, 0] + m[:, 1, 1] + m[:, 2, 2]
    decision = np.stack([m[:, 0, 0], m[:, 1, 1], m[:, 2, 2], trace], axis=-1)
    choice = np.argmax(decision, axis=-1)
    q = np.empty((len(m), 4))
    for i in range(3):
        j, k = (i + 1) % 3, (i + 2) % 3
        sel = choice == i
        ms, ts = m[sel], trace[sel]
        q[sel, i] = 1.0 - ts + 2.0 * ms[:, i, i]
        q[sel, j] = ms[:, j, i] + ms[:, i, j]
        q[sel, k] = ms[:, k, i] + ms[:, i, k]
        q[sel, 3] = ms[:, k, j] - ms[:, j, k]
    sel = choice == 3
    ms = m[sel]
    q[sel, 0] = ms[:, 2, 1] - ms[:, 1, 2]
    q[sel, 1] = ms[:, 0, 2] - ms[:, 2, 0]
    q[sel, 2] = ms[:, 1, 0] - ms[:, 0, 1]
    q[sel, 3] = 1.0 + trace[sel]
    return q


def matrices_to_quat_wxyz(rotations: np.ndarray) -> np.ndarray:
    """(N, 3, 3) -> (N, 4) unit w,x,y,z with w >= 0."""
    q_xyzw = matrices_to_quat_xyzw_raw(orthogonalise(rotations))
    q_xyzw /= np.linalg.norm(q_xyzw, axis=1)[:, None]
    q_wxyz = q_xyzw[:, [3, 0, 1, 2]]  # scipy-style x,y,z,w -> our w,x,y,z
    return q_wxyz * np.where(q_wxyz[:, :1] < 0.0, -1.0, 1.0)


def rotation_angles_rad(rotations: np.ndarray) -> np.ndarray:
    """Angle (rad, in [0, pi]) of each (N, 3, 3) rotation, as scipy's magnitude()."""
    if len(rotations) == 0:
        return np.zeros(0)
    q = matrices_to_quat_xyzw_raw(orthogonalise(rotations))
    q /= np.linalg.norm(q, axis=1)[:, None]
    return 2.0 * np.arctan2(np.linalg.norm(q[:, :3], axis=1), np.abs(q[:, 3]))


def inverse(a_from_b: np.ndarray) -> np.ndarray:
    """b_from_a for (N, 4, 4) rigid transforms (transpose rotation)."""
    rt = np.swapaxes(a_from_b[:, :3, :3], -1, -2)
    out = np.zeros_like(a_from_b)
    out[:, :3, :3] = rt
    out[:, :3, 3] = -np.einsum("nij,nj->ni", rt, a_from_b[:, :3, 3])
    out[:, 3, 3] = 1.0
    return out


def relative(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """a^-1 b for stacks of rigid transforms."""
    return inverse(a) @ b


def slerp_wxyz(q0: np.ndarray, q1: np.ndarray, fraction: np.ndarray) -> np.ndarray:
    """Spherical linear interpolation of (N, 4) unit quaternions, shortest path."""
    q0 = q0 / np.linalg.norm(q0, axis=1)[:, None]
    q1 = q1 / np.linalg.norm(q1, axis=1)[:, None]
    d = np.einsum("ij,ij->i", q0, q1)
    q1 = np.where(d[:, None] < 0.0, -q1, q1)
    d = np.abs(d)
    angle = np.arccos(np.clip(d, -1.0, 1.0))
    small = angle < 1e-9
    sin_angle = np.where(small, 1.0, np.sin(angle))
    w0 = np.where(small, 1.0 - fraction, np.sin((1.0 - fraction) * angle) / sin_angle)
    w1 = np.where(small, fraction, np.sin(fraction * angle) / sin_angle)
    out = w0[:, None] * q0 + w1[:, None] * q1
    return out / np.linalg.norm(out, axis=1)[:, None]


def yaw_rotation(yaw_rad: float) -> np.ndarray:
    """Rotation about +z."""
    c, s = np.cos(yaw_rad), np.sin(yaw_rad)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])

"""Rigid transforms and rotation conventions.

Transforms are 4x4 homogeneous matrices named ``a_from_b`` (they map points in frame b to frame a
and chain right to left: ``a_from_c = a_from_b @ b_from_c``). Rotations go through scipy's
``Rotation``; quaternion order is always in the name (``q_wxyz`` or ``q_xyzw``).
"""

from __future__ import annotations

import numpy as np

# scipy.spatial costs ~0.3 s to import; it is imported inside the functions that need it so that
# light commands (`slam eval`) start fast.


def make_transform(rotation: np.ndarray, translation: np.ndarray) -> np.ndarray:
    """Build a 4x4 transform from a 3x3 rotation and a 3-vector."""
    t = np.eye(4)
    t[:3, :3] = rotation
    t[:3, 3] = np.asarray(translation, dtype=float).reshape(3)
    return t


def invert_transform(a_from_b: np.ndarray) -> np.ndarray:
    """Return b_from_a for a rigid 4x4 (or a stack of them, shape (N, 4, 4))."""
    a_from_b = np.asarray(a_from_b, dtype=float)
    rot_t = np.swapaxes(a_from_b[..., :3, :3], -1, -2)
    out = np.zeros_like(a_from_b)
    out[..., :3, :3] = rot_t
    out[..., :3, 3] = -np.einsum("...ij,...j->...i", rot_t, a_from_b[..., :3, 3])
    out[..., 3, 3] = 1.0
    return out


def nearest_rigid(transform: np.ndarray) -> np.ndarray:
    """The rigid 4x4 closest to ``transform``: its rotation block projected onto SO(3) (SVD).

    Composing rigid transforms in floating point slowly loses orthonormality; a correction
    computed from such a pose and applied to every other pose feeds the error back, and it
    grows geometrically over thousands of corrections. Projecting the correction stops that.
    """
    u, _, vt = np.linalg.svd(transform[:3, :3])
    rot = u @ vt
    if np.linalg.det(rot) < 0:
        rot = u @ np.diag([1.0, 1.0, -1.0]) @ vt
    out = np.eye(4)
    out[:3, :3] = rot
    out[:3, 3] = transform[:3, 3]
    return out


def is_rigid(transforms: np.ndarray, tol: float) -> np.ndarray:
    """Per 4x4 in ``transforms`` (shape (..., 4, 4)): finite, rotation block orthonormal to
    within ``tol`` (max |R^T R - I|) and a proper rotation (det > 0)."""
    t = np.asarray(transforms, dtype=float)
    rot = np.where(np.isfinite(t[..., :3, :3]), t[..., :3, :3], 0.0)
    gram = np.swapaxes(rot, -1, -2) @ rot
    with np.errstate(invalid="ignore", over="ignore"):
        orthonormal = np.abs(gram - np.eye(3)).max(axis=(-2, -1)) <= tol
    return np.isfinite(t).all(axis=(-2, -1)) & orthonormal & (np.linalg.det(rot) > 0)


def transform_points(a_from_b: np.ndarray, points_b: np.ndarray) -> np.ndarray:
    """Map (N, 3) points from frame b to frame a."""
    return points_b @ a_from_b[:3, :3].T + a_from_b[:3, 3]


def quat_wxyz_to_matrix(q_wxyz: np.ndarray) -> np.ndarray:
    """(…, 4) w,x,y,z -> (…, 3, 3). scipy wants x,y,z,w, hence the reorder."""
    from scipy.spatial.transform import Rotation

    q = np.asarray(q_wxyz, dtype=float)
    return Rotation.from_quat(q[..., [1, 2, 3, 0]]).as_matrix()


def matrix_to_quat_wxyz(rotation: np.ndarray) -> np.ndarray:
    """(…, 3, 3) -> (…, 4) w,x,y,z with w >= 0 (scipy returns x,y,z,w)."""
    from scipy.spatial.transform import Rotation

    q_xyzw = Rotation.from_matrix(rotation).as_quat()
    q_wxyz = q_xyzw[..., [3, 0, 1, 2]]
    sign = np.where(q_wxyz[..., :1] < 0, -1.0, 1.0)
    return q_wxyz * sign


def poses_to_matrices(positions: np.ndarray, q_wxyz: np.ndarray) -> np.ndarray:
    """(N, 3) positions + (N, 4) q_wxyz -> (N, 4, 4) transforms."""
    n = len(positions)
    out = np.zeros((n, 4, 4))
    out[:, :3, :3] = quat_wxyz_to_matrix(q_wxyz)
    out[:, :3, 3] = positions
    out[:, 3, 3] = 1.0
    return out


def skew(v: np.ndarray) -> np.ndarray:
    """The 3x3 cross-product matrix of v."""
    x, y, z = v
    return np.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]])


def skew_batch(v: np.ndarray) -> np.ndarray:
    """Cross-product matrices (N, 3, 3) of vectors (N, 3)."""
    out = np.zeros((len(v), 3, 3))
    out[:, 0, 1], out[:, 0, 2], out[:, 1, 2] = -v[:, 2], v[:, 1], -v[:, 0]
    out[:, 1, 0], out[:, 2, 0], out[:, 2, 1] = v[:, 2], -v[:, 1], v[:, 0]
    return out


def so3_exp(omega: np.ndarray) -> np.ndarray:
    """Rotation matrix for one rotation vector (rad), by Rodrigues' formula (:func:`so3_exp_batch`)."""
    return so3_exp_batch(omega)[0]


def so3_exp_batch(omegas: np.ndarray) -> np.ndarray:
    """Rotation matrices (N, 3, 3) for rotation vectors (N, 3) (rad), by Rodrigues' formula.

    Written out (not scipy) because the front end's IMU prior calls it every frame: a scipy
    Rotation costs more to build than the few samples between two frames take to integrate.
    """
    w = np.asarray(omegas, dtype=float).reshape(-1, 3)
    theta2 = np.einsum("ni,ni->n", w, w)
    k = np.zeros((len(w), 3, 3))
    k[:, 0, 1], k[:, 0, 2], k[:, 1, 2] = -w[:, 2], w[:, 1], -w[:, 0]
    k[:, 1, 0], k[:, 2, 0], k[:, 2, 1] = w[:, 2], -w[:, 1], w[:, 0]
    small = theta2 < 1e-12
    theta = np.sqrt(np.where(small, 1.0, theta2))
    a = np.where(small, 1.0, np.sin(theta) / theta)
    b = np.where(small, 0.5, (1.0 - np.cos(theta)) / np.where(small, 1.0, theta2))
    return np.eye(3) + a[:, None, None] * k + b[:, None, None] * (k @ k)


def so3_right_jacobian(omega: np.ndarray) -> np.ndarray:
    """Right Jacobian J_r (3x3) of SO(3) at rotation vector ``omega`` (rad):
    ``exp(omega + d) ~= exp(omega) @ exp(J_r(omega) @ d)``; the left one is ``J_r(-omega)``."""
    w = np.asarray(omega, dtype=float).reshape(3)
    theta2 = float(w @ w)
    k = skew(w)
    if theta2 < 1e-12:
        return np.eye(3) - 0.5 * k + (k @ k) / 6.0
    theta = np.sqrt(theta2)
    a = (1.0 - np.cos(theta)) / theta2
    b = (theta - np.sin(theta)) / (theta2 * theta)
    return np.eye(3) - a * k + b * (k @ k)


def rotation_angle_rad(rotation: np.ndarray) -> float:
    """Angle (rad, in [0, pi]) of a 3x3 rotation matrix: the norm of its rotation vector.

    ``atan2(|vee(R - R^T)| / 2, (trace R - 1) / 2)``: exact near 0 and near pi alike (an
    arccos of the trace alone loses ~1e-8 rad near 0) and without building a scipy Rotation.
    """
    r = np.asarray(rotation, dtype=float)
    sin = 0.5 * np.linalg.norm([r[2, 1] - r[1, 2], r[0, 2] - r[2, 0], r[1, 0] - r[0, 1]])
    cos = 0.5 * (r[0, 0] + r[1, 1] + r[2, 2] - 1.0)
    return float(np.arctan2(sin, cos))


def so3_log(rotation: np.ndarray) -> np.ndarray:
    """Rotation vector (rad) of a rotation matrix (3, 3), or vectors (N, 3) of matrices (N, 3, 3)."""
    from scipy.spatial.transform import Rotation

    return Rotation.from_matrix(rotation).as_rotvec()


def scale_body_pose(
    world_from_body: np.ndarray, scale: float, body_from_cam: np.ndarray
) -> np.ndarray:
    """world_from_body of a monocular map scaled by ``scale`` about its origin: the camera
    centre scales (it is what monocular structure from motion measures), the rigid
    camera-body lever arm does not."""
    world_from_cam = np.asarray(world_from_body, float) @ body_from_cam
    world_from_cam[:3, 3] *= scale
    return world_from_cam @ invert_transform(body_from_cam)

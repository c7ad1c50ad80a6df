"""Frame-to-frame rotations of one camera from its images alone.

Per pair of consecutive frames: corners (``cv2.goodFeaturesToTrack``), pyramidal KLT with a
forward-backward check (:mod:`slam.frontend.features`' tracker), undistortion to normalised
coordinates, then an essential matrix (RANSAC) and ``cv2.recoverPose``. Where the translation
is too small for an essential matrix (parallax below ``min_parallax_rad``), the rotation comes
from a RANSAC homography instead (a pure rotation: ``H = R`` in normalised coordinates, made
orthonormal). The result is the rotation vector of cam(t0)_from_cam(t1), i.e. the camera's
angular motion over the pair, in the camera frame.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass

import cv2
import numpy as np
from scipy.spatial.transform import Rotation

from slam.core.calibration import CameraIntrinsics

MIN_TRACKS = 25
CALIB_KLT_BACKWARD_LEVELS = 1


@dataclass(frozen=True, eq=False)
class VisualRotations:
    """Per consecutive frame pair k (M,): stamps t0_ns, t1_ns (int64), the rotation vector of
    cam(t0)_from_cam(t1) in rad (M, 3), inlier count; pairs that failed are left out."""

    t0_ns: np.ndarray
    t1_ns: np.ndarray
    rotvec_cam_rad: np.ndarray
    inliers: np.ndarray
    pairs_tried: int

    @property
    def rate_rad_s(self) -> np.ndarray:
        """Angular rate magnitude of each pair (rad/s)."""
        dt_s = (self.t1_ns - self.t0_ns) * 1e-9
        return np.linalg.norm(self.rotvec_cam_rad, axis=1) / dt_s


def _track(prev: np.ndarray, cur: np.ndarray, max_corners: int) -> tuple[np.ndarray, np.ndarray]:
    from slam.config import FrontendConfig
    from slam.frontend.features import track_klt

    corners = cv2.goodFeaturesToTrack(prev, max_corners, 0.01, 12, blockSize=5)
    if corners is None:
        return np.zeros((0, 2)), np.zeros((0, 2))
    p0 = corners.reshape(-1, 2).astype(np.float32)
    # its own KLT settings, not the front end's tuning of the moment: with the front end's
    # base-level backward check the camera-IMU rotation of tests/test_calib_check.py came out
    # 0.66 deg off the truth, with one level as before
    p1, ok = track_klt(prev, cur, p0, FrontendConfig(klt_backward_levels=CALIB_KLT_BACKWARD_LEVELS))
    return p0[ok].astype(np.float64), p1[ok].astype(np.float64)


def pair_rotation(
    x0: np.ndarray, x1: np.ndarray, threshold_rad: float = 1.5e-3, min_parallax_rad: float = 2e-3
) -> tuple[np.ndarray, int] | None:
    """cam0_from_cam1 rotation vector from normalised matches x0 -> x1 (N, 2), and inliers."""
    if len(x0) < MIN_TRACKS:
        return None
    from slam.frontend.features import essential_ransac

    found = essential_ransac(x0, x1, threshold_rad)
    rot_1_from_0 = None
    inliers = 0
    if found is not None:
        e, mask = found
        n_in, r, _t, mask2 = cv2.recoverPose(e, x0, x1, np.eye(3), mask=mask)
        inliers = int(n_in)
        # parallax left after removing the rotation: too little and E is ill-conditioned
        x0h = np.hstack([x0, np.ones((len(x0), 1))])
        rotated = x0h @ r.T
        rotated = rotated[:, :2] / rotated[:, 2:3]
        parallax = float(np.median(np.linalg.norm(rotated - x1, axis=1)))
        if parallax >= min_parallax_rad and inliers >= MIN_TRACKS:
            rot_1_from_0 = r
    if rot_1_from_0 is None:
        h, hmask = cv2.findHomography(x0, x1, cv2.RANSAC, threshold_rad)
        if h is None or hmask is None or int(hmask.sum()) < MIN_TRACKS:
            return None
        u, _s, vt = np.linalg.svd(h)
        r = u @ vt
        if np.linalg.det(r) < 0:
            return None
        rot_1_from_0, inliers = r, int(hmask.sum())
    return Rotation.from_matrix(rot_1_from_0.T).as_rotvec(), inliers


def visual_rotations(
    frames: Iterable[tuple[int, np.ndarray]],
    intrinsics: CameraIntrinsics,
    max_corners: int = 300,
) -> VisualRotations:
    """Rotations between consecutive (t_ns, grey image) frames of one camera."""
    t0s, t1s, vecs, inl = [], [], [], []
    prev: tuple[int, np.ndarray] | None = None
    tried = 0
    for t_ns, image in frames:
        if prev is not None:
            tried += 1
            p0, p1 = _track(prev[1], image, max_corners)
            if len(p0) >= MIN_TRACKS:
                res = pair_rotation(
                    intrinsics.undistort_points(p0), intrinsics.undistort_points(p1)
                )
                if res is not None:
                    t0s.append(prev[0])
                    t1s.append(t_ns)
                    vecs.append(res[0])
                    inl.append(res[1])
        prev = (int(t_ns), image)
    return VisualRotations(
        t0_ns=np.array(t0s, dtype=np.int64),
        t1_ns=np.array(t1s, dtype=np.int64),
        rotvec_cam_rad=np.array(vecs, dtype=np.float64).reshape(-1, 3),
        inliers=np.array(inl, dtype=np.int64),
        pairs_tried=tried,
    )

"""Geometric verification of a loop candidate: ORB matching, then PnP RANSAC.

Pure functions over arrays, so any stage can call them: the query keyframe's keypoints and
descriptors, the candidate keyframe's descriptors and the 3-D points of its keypoints (NaN
where a keypoint has no landmark), and the query camera's intrinsics.

The 3-D points may be in the candidate camera frame (the usual case: the returned pose is then
``candidate_cam_from_query_cam``) or in any other frame F (e.g. world: the returned pose is
then ``F_from_query_cam``).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from slam.core.geometry import invert_transform, make_transform


@dataclass(frozen=True)
class VerifyParams:
    """Thresholds of the geometric check (defaults close to ORB-SLAM's)."""

    ratio: float = 0.8
    """Lowe ratio test: best / second-best Hamming distance must be below this."""
    max_hamming: int = 64
    """Reject matches farther than this many bits (of 256)."""
    min_matches: int = 20
    """Give up before RANSAC with fewer descriptor matches to landmarks."""
    min_inliers: int = 20
    """Accept only with at least this many PnP inliers ..."""
    min_inlier_ratio: float = 0.3
    """... making up at least this fraction of the matches."""
    reprojection_px: float = 3.0
    """RANSAC inlier threshold (pixels)."""
    ransac_iterations: int = 300
    confidence: float = 0.999


@dataclass(frozen=True, eq=False)
class LoopVerification:
    """A verified loop: the relative pose and the evidence behind it."""

    candidate_cam_from_query_cam: np.ndarray  # 4x4 (F_from_query_cam if points are in F)
    num_inliers: int
    num_matches: int
    query_indices: np.ndarray  # (num_inliers,) query keypoint index of each inlier
    candidate_indices: np.ndarray  # (num_inliers,) candidate keypoint index of each inlier
    rms_reprojection_px: float


def match_descriptors(
    query_desc: np.ndarray,
    candidate_desc: np.ndarray,
    ratio: float = 0.8,
    max_hamming: int = 64,
) -> tuple[np.ndarray, np.ndarray]:
    """Hamming matches with a ratio test and one-to-one filtering.

    Returns (query indices, candidate indices), each (M,) int64.
    """
    empty = (np.zeros(0, np.int64), np.zeros(0, np.int64))
    if len(query_desc) == 0 or len(candidate_desc) < 2:
        return empty
    matcher = cv2.BFMatcher(cv2.NORM_HAMMING, crossCheck=False)
    knn = matcher.knnMatch(query_desc, candidate_desc, k=2)
    q_idx, c_idx, dists = [], [], []
    for pair in knn:
        if len(pair) < 2:
            continue
        best, second = pair
        if best.distance <= max_hamming and best.distance < ratio * second.distance:
            q_idx.append(best.queryIdx)
            c_idx.append(best.trainIdx)
            dists.append(best.distance)
    if not q_idx:
        return empty
    q = np.array(q_idx, dtype=np.int64)
    c = np.array(c_idx, dtype=np.int64)
    # One-to-one: when several query keypoints pick one candidate keypoint, keep the closest.
    order = np.argsort(np.array(dists), kind="stable")
    _, first = np.unique(c[order], return_index=True)
    keep = np.sort(order[first])
    return q[keep], c[keep]


def verify_loop(
    query_xy_px: np.ndarray,
    query_desc: np.ndarray,
    candidate_desc: np.ndarray,
    candidate_points: np.ndarray,
    camera_matrix: np.ndarray,
    dist_coeffs: np.ndarray | None = None,
    params: VerifyParams | None = None,
) -> LoopVerification | None:
    """Check a loop candidate geometrically; None when it fails.

    ``query_xy_px`` (N, 2) and ``query_desc`` (N, 32): the query keyframe's keypoints (pixels
    in the image ``camera_matrix``/``dist_coeffs`` describe). ``candidate_desc`` (M, 32) and
    ``candidate_points`` (M, 3): the candidate's keypoints with their landmarks (metres, NaN
    rows for keypoints without one).
    """
    p = params or VerifyParams()
    points = np.asarray(candidate_points, dtype=np.float64)
    has_point = np.all(np.isfinite(points), axis=1)
    if has_point.sum() < p.min_matches:
        return None
    cand_rows = np.flatnonzero(has_point)
    q_idx, c_sub = match_descriptors(
        query_desc, candidate_desc[cand_rows], ratio=p.ratio, max_hamming=p.max_hamming
    )
    if len(q_idx) < p.min_matches:
        return None
    c_idx = cand_rows[c_sub]
    obj = np.ascontiguousarray(points[c_idx], dtype=np.float64)
    img = np.ascontiguousarray(query_xy_px[q_idx], dtype=np.float64)
    k = np.asarray(camera_matrix, dtype=np.float64)
    dist = None if dist_coeffs is None else np.asarray(dist_coeffs, dtype=np.float64)
    ok, rvec, tvec, inliers = cv2.solvePnPRansac(
        obj,
        img,
        k,
        dist,
        iterationsCount=p.ransac_iterations,
        reprojectionError=p.reprojection_px,
        confidence=p.confidence,
        flags=cv2.SOLVEPNP_SQPNP,
    )
    if not ok or inliers is None:
        return None
    inl = inliers.reshape(-1)
    if len(inl) < p.min_inliers:
        return None
    # Refine on the inliers, then re-select inliers with the refined pose.
    rvec, tvec = cv2.solvePnPRefineLM(obj[inl], img[inl], k, dist, rvec, tvec)
    projected, _ = cv2.projectPoints(obj, rvec, tvec, k, dist)
    err = np.linalg.norm(projected.reshape(-1, 2) - img, axis=1)
    in_front = (obj @ cv2.Rodrigues(rvec)[0].T + tvec.reshape(3))[:, 2] > 0
    inl = np.flatnonzero((err < p.reprojection_px) & in_front)
    if len(inl) < p.min_inliers or len(inl) < p.min_inlier_ratio * len(q_idx):
        return None
    query_cam_from_candidate = make_transform(cv2.Rodrigues(rvec)[0], tvec.reshape(3))
    return LoopVerification(
        candidate_cam_from_query_cam=invert_transform(query_cam_from_candidate),
        num_inliers=int(len(inl)),
        num_matches=int(len(q_idx)),
        query_indices=q_idx[inl],
        candidate_indices=c_idx[inl],
        rms_reprojection_px=float(np.sqrt(np.mean(err[inl] ** 2))),
    )


def _project(points: np.ndarray, k: np.ndarray) -> np.ndarray:
    return points[:, :2] / points[:, 2:3] * [k[0, 0], k[1, 1]] + [k[0, 2], k[1, 2]]


def refine_symmetric(
    candidate_cam_from_query_cam: np.ndarray,
    candidate_points: np.ndarray,
    query_xy_px: np.ndarray,
    query_points: np.ndarray,
    candidate_xy_px: np.ndarray,
    camera_matrix: np.ndarray,
    huber_px: float = 1.0,
) -> np.ndarray:
    """Refine a relative pose on matched landmarks seen by both keyframes.

    Minimises (Huber) the reprojection errors in *both* directions: candidate points into the
    query image and query points into the candidate image, so each side's depth errors (stereo:
    they grow with depth squared) are balanced by the other's. Rows of ``query_points`` that
    are NaN only contribute the first direction. Returns ``candidate_cam_from_query_cam``.
    """
    from scipy.optimize import least_squares
    from scipy.spatial.transform import Rotation

    k = np.asarray(camera_matrix, dtype=np.float64)
    pc = np.asarray(candidate_points, dtype=np.float64)
    pq = np.asarray(query_points, dtype=np.float64)
    uq = np.asarray(query_xy_px, dtype=np.float64)
    uc = np.asarray(candidate_xy_px, dtype=np.float64)
    both = np.all(np.isfinite(pq), axis=1)
    pq, uc = pq[both], uc[both]
    t0 = np.asarray(candidate_cam_from_query_cam, dtype=np.float64)
    x0 = np.concatenate([Rotation.from_matrix(t0[:3, :3]).as_rotvec(), t0[:3, 3]])

    def residuals(x: np.ndarray) -> np.ndarray:
        rot = Rotation.from_rotvec(x[:3]).as_matrix()
        t = x[3:]
        pc_in_q = (pc - t) @ rot  # rot^T (pc - t): candidate points in the query camera
        pq_in_c = pq @ rot.T + t
        r1 = _project(pc_in_q, k) - uq
        r2 = _project(pq_in_c, k) - uc
        return np.concatenate([r1.ravel(), r2.ravel()])

    sol = least_squares(residuals, x0, loss="huber", f_scale=huber_px, x_scale="jac")
    if not sol.success or not np.all(np.isfinite(sol.x)):
        return t0
    return make_transform(Rotation.from_rotvec(sol.x[:3]).as_matrix(), sol.x[3:])


def verify_loop_landmarks(
    query_xy_px: np.ndarray,
    query_desc: np.ndarray,
    query_points: np.ndarray,
    candidate_xy_px: np.ndarray,
    candidate_desc: np.ndarray,
    candidate_points: np.ndarray,
    camera_matrix: np.ndarray,
    params: VerifyParams | None = None,
) -> LoopVerification | None:
    """Verify a loop between two keyframes' *landmark observations* (both sides: undistorted
    front-end pixels, ORB descriptors computed there, 3-D points in their own camera frames).

    Why not the query's whole-image ORB keypoints (``verify_loop``): FAST corners sit a pixel
    or two from the front end's Shi-Tomasi corners their descriptors match, which biased the
    relative pose. Measured on synthetic keyframes with exact landmarks (figure8, 60 revisits):
    7.0 mm / 0.15 deg median error with ORB keypoints, 1.6 mm / 0.04 deg landmark to landmark
    (118 instead of 54 inliers); with stereo-like depth noise the symmetric refinement
    (:func:`refine_symmetric`) takes 2.5 mm to 2.0 mm. Returns ``candidate_cam_from_query_cam``.
    """
    p = params or VerifyParams()
    res = verify_loop(
        query_xy_px, query_desc, candidate_desc, candidate_points, camera_matrix, None, p
    )
    if res is None:
        return None
    qi, ci = res.query_indices, res.candidate_indices
    pose = refine_symmetric(
        res.candidate_cam_from_query_cam,
        np.asarray(candidate_points, dtype=np.float64)[ci],
        np.asarray(query_xy_px, dtype=np.float64)[qi],
        np.asarray(query_points, dtype=np.float64)[qi],
        np.asarray(candidate_xy_px, dtype=np.float64)[ci],
        camera_matrix,
        huber_px=1.0,
    )
    # Inliers again under the refined pose (candidate points into the query image).
    k = np.asarray(camera_matrix, dtype=np.float64)
    pc = np.asarray(candidate_points, dtype=np.float64)[ci]
    in_q = (pc - pose[:3, 3]) @ pose[:3, :3]
    front = in_q[:, 2] > 0
    err = np.full(len(ci), np.inf)
    err[front] = np.linalg.norm(
        _project(in_q[front], k) - np.asarray(query_xy_px)[qi][front], axis=1
    )
    keep = err < p.reprojection_px
    if keep.sum() < p.min_inliers:
        return None
    return LoopVerification(
        candidate_cam_from_query_cam=pose,
        num_inliers=int(keep.sum()),
        num_matches=res.num_matches,
        query_indices=qi[keep],
        candidate_indices=ci[keep],
        rms_reprojection_px=float(np.sqrt(np.mean(err[keep] ** 2))),
    )

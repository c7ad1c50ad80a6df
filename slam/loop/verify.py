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

from slam.geometry import invert_transform, make_transform


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

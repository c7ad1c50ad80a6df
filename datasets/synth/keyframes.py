"""Keyframes built from a synthetic sequence's ground truth, with injected odometry drift.

For tests and benchmarks of the loop closer and relocaliser without running the front end:
corners of the rendered left image get their true depth; the keyframe's "VO" pose and landmark
positions are the truth moved by a drift transform that grows with time (a yaw about the first
position plus a translation), so they stay mutually consistent as a front end's would.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from datasets.synth.generator import SyntheticSequence
from slam.core.geometry import make_transform, so3_exp
from slam.core.messages import Keyframe


@dataclass(frozen=True)
class Drift:
    """Odometry drift that grows linearly with time since the first keyframe."""

    yaw_deg_per_s: float = 0.0
    translation_m_per_s: tuple[float, float, float] = (0.0, 0.0, 0.0)

    def at(self, dt_s: float, pivot_m: np.ndarray) -> np.ndarray:
        """drifted_world_from_world after ``dt_s`` seconds (rotation about ``pivot_m``)."""
        rot = so3_exp(np.array([0.0, 0.0, np.radians(self.yaw_deg_per_s * dt_s)]))
        trans = pivot_m - rot @ pivot_m + np.asarray(self.translation_m_per_s) * dt_s
        return make_transform(rot, trans)


@dataclass(frozen=True, eq=False)
class SyntheticKeyframe:
    keyframe: Keyframe
    world_from_body_odom: np.ndarray  # drifted (= keyframe.world_from_body_vo)
    world_from_body_true: np.ndarray


def ground_truth_keyframes(
    seq: SyntheticSequence,
    frame_indices: list[int] | np.ndarray,
    drift: Drift | None = None,
    max_corners: int = 250,
    segment_id: int = 0,
    first_keyframe_id: int = 0,
    first_landmark_id: int = 0,
) -> list[SyntheticKeyframe]:
    """One keyframe per frame index: image, corners with true depth, drifted poses."""
    drift = drift or Drift()
    cam = seq.calibration.cameras[0]
    intr = cam.intrinsics
    renderer = seq.renderer.cameras[0]
    times = seq.frame_times_ns()
    t0 = int(times[frame_indices[0]])
    pivot = seq.world_from_body_at(t0)[:3, 3]
    out: list[SyntheticKeyframe] = []
    next_lm = first_landmark_id
    for n, idx in enumerate(frame_indices):
        t_ns = int(times[idx])
        world_from_body = seq.world_from_body_at(t_ns)
        world_from_cam = world_from_body @ cam.body_from_cam
        render = renderer.render(world_from_cam, with_depth=True)
        assert render.depth_m is not None
        image = render.image
        corners = cv2.goodFeaturesToTrack(image, max_corners, 0.01, 12)
        px = np.zeros((0, 2)) if corners is None else corners.reshape(-1, 2).astype(np.float64)
        rc = np.round(px).astype(int)
        depth = render.depth_m[rc[:, 1], rc[:, 0]].astype(np.float64)
        ok = np.isfinite(depth) & (depth > 0.2) & (depth < 25.0)
        px, depth = px[ok], depth[ok]
        norm = intr.undistort_points(px)
        pts_cam = np.column_stack([norm * depth[:, None], depth])
        pts_world = pts_cam @ world_from_cam[:3, :3].T + world_from_cam[:3, 3]
        d = drift.at((t_ns - t0) * 1e-9, pivot)
        odom = d @ world_from_body
        pts_odom = pts_world @ d[:3, :3].T + d[:3, 3]
        ids = np.arange(next_lm, next_lm + len(px), dtype=np.int64)
        next_lm += len(px)
        kf = Keyframe(
            t_ns=t_ns,
            keyframe_id=first_keyframe_id + n,
            frame_index=int(idx),
            segment_id=segment_id,
            world_from_body_vo=odom,
            landmark_ids=ids,
            pixels_left_undist=norm * [intr.fx, intr.fy] + [intr.cx, intr.cy],
            pixels_right_undist=np.full((len(px), 2), np.nan),
            points_world_vo=pts_odom,
            image_left=image,
            image_right=None,
        )
        out.append(SyntheticKeyframe(kf, odom, world_from_body))
    return out

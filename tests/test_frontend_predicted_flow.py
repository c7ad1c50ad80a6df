"""KLT started at each landmark's projection from the predicted pose, on few pyramid levels
(``FrontEnd._track_points``); the constant-velocity pose prediction; the reduced images of
``brightness_ratio`` computed once per image."""

from __future__ import annotations

import dataclasses

import cv2
import numpy as np
from scipy.spatial.transform import Rotation
from synthetic_planes import PlaneScene, look_at

from slam.config import FrontendConfig
from slam.core.calibration import Calibration, CameraCalibration, CameraIntrinsics
from slam.core.geometry import make_transform, so3_exp, transform_points
from slam.frontend.features import ReducedImages, brightness_ratio
from slam.frontend.tracker import FrontEnd

W, H, F = 320, 240, 220.0
INTR = CameraIntrinsics(W, H, F, F, W / 2, H / 2)


def _front_end(cfg: FrontendConfig) -> FrontEnd:
    right = make_transform(np.eye(3), np.array([0.11, 0.0, 0.0]))
    calib = Calibration(
        (CameraCalibration("cam0", INTR), CameraCalibration("cam1", INTR, body_from_cam=right))
    )
    return FrontEnd(calib, cfg)


def _two_views() -> tuple[FrontEnd, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """A front end tracking landmarks (true 3-D points) seen in a first view; the second view
    8 cm and 3 degrees away (~20 px of flow). Returns (front end, image 0, image 1, pose 1,
    the landmarks' true pixels in image 1)."""
    scene = PlaneScene(seed=2)
    pose0 = look_at(np.array([0.0, 0.0, 1.3]), np.array([1.5, 0.3, 1.0]))
    step = make_transform(so3_exp(np.radians([1.0, -2.5, 1.0])), np.array([0.06, -0.03, 0.04]))
    pose1 = pose0 @ step
    img0, depth0 = scene.render(pose0, INTR.K, (H, W))
    img1, _ = scene.render(pose1, INTR.K, (H, W))
    corners = cv2.goodFeaturesToTrack(img0, 150, 0.01, 10).reshape(-1, 2)
    z = depth0[corners[:, 1].astype(int), corners[:, 0].astype(int)].astype(float)
    rays = np.hstack([(corners - [INTR.cx, INTR.cy]) / F, np.ones((len(corners), 1))])
    world = transform_points(pose0, rays * z[:, None])
    truth = INTR.project(transform_points(np.linalg.inv(pose1), world))
    inside = (truth > 15).all(axis=1) & (truth < [W - 15, H - 15]).all(axis=1)
    fe = _front_end(dataclasses.replace(FrontendConfig(), klt_predicted_levels=1))
    fe.px = corners[inside].astype(np.float32)
    fe.ids = np.arange(int(inside.sum()), dtype=np.int64)
    fe.landmarks = {i: p for i, p in enumerate(world[inside])}
    return fe, img0, img1, pose1, truth[inside]


def test_tracks_started_at_the_predicted_projection_land_on_the_truth() -> None:
    fe, img0, img1, pose1, truth = _two_views()
    px, ok = fe._track_points(img0, img1, None, pose1, np.ones(len(fe.px), bool))
    err = np.linalg.norm(px - truth, axis=1)[ok]
    assert ok.mean() > 0.9
    assert np.median(err) < 0.1 and np.percentile(err, 90) < 0.3
    assert fe.stats.klt_predicted == len(truth)
    assert fe.stats.klt_retracked < 0.1 * len(truth)


def test_a_bad_prediction_falls_back_to_the_full_pyramid() -> None:
    """A predicted pose 35 cm off (tens of pixels): one pyramid level cannot reach the
    points; they are tracked again over the full pyramid and end as well as with a good one."""
    fe, img0, img1, pose1, truth = _two_views()
    wrong = pose1 @ make_transform(np.eye(3), np.array([0.35, 0.0, 0.0]))
    px, ok = fe._track_points(img0, img1, None, wrong, np.ones(len(fe.px), bool))
    err = np.linalg.norm(px - truth, axis=1)[ok]
    assert ok.mean() > 0.9
    assert np.median(err) < 0.1
    assert fe.stats.klt_retracked > 0.5 * len(truth)


def test_constant_velocity_prediction_extrapolates_the_last_motion() -> None:
    fe = _front_end(FrontendConfig())
    prev = make_transform(so3_exp(np.array([0.1, -0.2, 0.3])), np.array([1.0, 2.0, 0.5]))
    delta = make_transform(so3_exp(np.array([0.02, 0.05, -0.03])), np.array([0.03, 0.0, -0.01]))
    fe.prev_world_from_body = prev
    fe.world_from_body = prev @ delta
    fe.t_prev_ns, fe.prev_dt_ns = 1_000, 100
    pred = fe._predict_pose(1_150, None)  # 1.5 frame intervals ahead
    rotvec = Rotation.from_matrix(delta[:3, :3]).as_rotvec() * 1.5
    expect = fe.world_from_body @ make_transform(
        Rotation.from_rotvec(rotvec).as_matrix(), delta[:3, 3] * 1.5
    )
    np.testing.assert_allclose(pred, expect, atol=1e-12)


def test_reduced_images_give_the_same_ratio_and_are_made_once() -> None:
    rng = np.random.default_rng(0)
    a = cv2.GaussianBlur(rng.uniform(0, 255, (480, 752)).astype(np.float32), (0, 0), 3)
    a = np.clip(a * 2 - 100, 20, 230).astype(np.uint8)
    b = cv2.convertScaleAbs(a, alpha=1.2)
    pts = rng.uniform(20, 460, (60, 2)).astype(np.float32)
    cache = ReducedImages()
    assert brightness_ratio(a, b, pts, pts, cache) == brightness_ratio(a, b, pts, pts)
    small_a = cache.get(a)
    assert cache.get(a) is small_a  # not reduced again
    c = b.copy()
    cache.get(c)
    cache.get(np.zeros_like(a))
    assert cache.get(b) is not None and len(cache._items) == 3


def test_bench_ground_truth_prior_has_the_pose_and_velocity_of_the_truth() -> None:
    from slam.core.trajectory import Trajectory
    from tools.bench_frontend import _truth_estimate

    t_ns = np.arange(0, 2_000_000_000, 5_000_000, dtype=np.int64)
    velocity = np.array([0.5, -0.2, 0.1])
    poses = np.repeat(np.eye(4)[None], len(t_ns), axis=0)
    poses[:, :3, 3] = t_ns[:, None] * 1e-9 * velocity
    poses[:, :3, :3] = so3_exp(np.array([0.0, 0.0, 0.3]))
    truth = Trajectory.from_matrices(t_ns, poses)
    est = _truth_estimate(truth, truth.matrices(), 1_000_000_000, 7)
    assert est.initialized and est.keyframe_id == 7 and est.t_ns == 1_000_000_000
    np.testing.assert_allclose(est.world_from_body, poses[200], atol=1e-12)
    np.testing.assert_allclose(est.velocity_world_m_s, velocity, atol=1e-9)

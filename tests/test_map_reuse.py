"""Map reuse: landmarks the front end stopped tracking are found again when the camera comes
back, and pull a drifted pose back onto them (``slam/frontend/landmark_map.py``)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from synthetic_planes import PlaneScene, look_at

from slam.config import FrontendConfig
from slam.core.calibration import Calibration, CameraCalibration, CameraIntrinsics
from slam.core.geometry import invert_transform, make_transform, so3_exp
from slam.core.messages import StereoFrame
from slam.frontend.landmark_map import LandmarkMap, SearchParams
from slam.frontend.tracker import FrontEnd

W, H, F = 320, 240, 220.0
BASELINE_M = 0.11
INTR = CameraIntrinsics(W, H, F, F, W / 2, H / 2)


def _calibration() -> Calibration:
    right = make_transform(np.eye(3), np.array([BASELINE_M, 0.0, 0.0]))
    return Calibration(
        (CameraCalibration("cam0", INTR), CameraCalibration("cam1", INTR, body_from_cam=right))
    )


def _circle(n_frames: int, frames_per_turn: int) -> list[np.ndarray]:
    """world_from_cam on a small circle in a room, looking outwards: a full turn comes back
    to where it started."""
    out = []
    for i in range(n_frames):
        a = 2 * np.pi * i / frames_per_turn
        eye = np.array([0.4 * np.cos(a) - 0.3, 0.4 * np.sin(a) - 0.2, 1.3])
        out.append(look_at(eye, eye + np.array([np.cos(a), np.sin(a), -0.35])))
    return out


def _stereo(scene: PlaneScene, world_from_cam: np.ndarray, t_ns: int, i: int) -> StereoFrame:
    cam0_from_cam1 = make_transform(np.eye(3), np.array([BASELINE_M, 0.0, 0.0]))
    left, _ = scene.render(world_from_cam, INTR.K, (H, W))
    right, _ = scene.render(world_from_cam @ cam0_from_cam1, INTR.K, (H, W))
    return StereoFrame(t_ns, left, right, i)


@pytest.fixture(scope="module")
def circle_frames() -> tuple[list[StereoFrame], list[np.ndarray]]:
    scene = PlaneScene(seed=3)
    poses = _circle(135, 120)
    frames = [_stereo(scene, p, i * 50_000_000, i) for i, p in enumerate(poses)]
    return frames, poses


def _run_with_drift(frames, poses, reuse: bool) -> tuple[list[float], FrontEnd]:
    """Track the circle; at frame 100, before the start comes back into view, move the front
    end's pose and local map by 4 cm and 1 degree (what drift does). Returns each frame's
    position error (m) against the truth in the first camera's frame."""
    cfg = dataclasses.replace(FrontendConfig(), map_reuse=reuse, map_min_inliers_alone=20)
    fe = FrontEnd(_calibration(), cfg)
    first_inv = invert_transform(poses[0])
    errors = []
    for i, frame in enumerate(frames):
        if i == 100:
            drift = make_transform(
                so3_exp(np.radians([0.0, 0.0, 1.0])), np.array([0.04, -0.02, 0.01])
            )
            fe._move_world(drift)
        result, _ = fe.process(frame)
        assert result.world_from_body is not None, f"frame {i} lost: {result.reason}"
        truth = first_inv @ poses[i]
        errors.append(float(np.linalg.norm(result.world_from_body[:3, 3] - truth[:3, 3])))
    return errors, fe


def test_a_revisit_pulls_a_drifted_pose_back(circle_frames) -> None:
    frames, poses = circle_frames
    with_reuse, fe = _run_with_drift(frames, poses, reuse=True)
    without, _ = _run_with_drift(frames, poses, reuse=False)
    assert max(with_reuse[:100]) < 0.015  # before the drift: the visual odometry's own
    assert min(without[125:]) > 0.03  # without map reuse the 4 cm stay
    assert max(with_reuse[125:]) < 0.015  # with it, the old landmarks pulled the pose back
    st = fe.stats
    assert st.map_corrections >= 1 and st.map_reobserved >= 20
    assert st.revisit_landmarks_old / st.revisit_landmarks >= 0.5


def _wall_points(
    scene: PlaneScene, world_from_cam: np.ndarray, n: int
) -> tuple[np.ndarray, np.ndarray]:
    """Well-textured pixels of a view and their exact world points."""
    import cv2

    img, depth = scene.render(world_from_cam, INTR.K, (H, W))
    px = cv2.goodFeaturesToTrack(img, n, 0.01, 10).reshape(-1, 2)
    px = px[(px[:, 0] > 20) & (px[:, 0] < W - 20) & (px[:, 1] > 20) & (px[:, 1] < H - 20)]
    z = depth[px[:, 1].round().astype(int), px[:, 0].round().astype(int)]
    rays = np.hstack([(px - [INTR.cx, INTR.cy]) / F, np.ones((len(px), 1))]) * z[:, None]
    return px, rays @ world_from_cam[:3, :3].T + world_from_cam[:3, 3]


PARAMS = SearchParams(
    radius_px=12,
    min_ncc=0.8,
    max_candidates=200,
    max_view_angle_deg=35,
    max_scale_change=1.5,
    half_window_px=7,
    max_rms=20.0,
)


def _map_from_view(scene: PlaneScene, birth: np.ndarray) -> LandmarkMap:
    img, _ = scene.render(birth, INTR.K, (H, W))
    px, pts = _wall_points(scene, birth, 150)
    # re-take the pixels exactly where the points project (goodFeaturesToTrack's are rounded)
    cam = (pts - birth[:3, 3]) @ birth[:3, :3]
    px = INTR.project(cam)
    lm = LandmarkMap(capacity=1000)
    ids = np.arange(len(pts))
    lm.add(ids, pts, px, img, birth, INTR, segment=0, keyframe_id=0, refined=True)
    lm.retire(ids, pts)
    return lm


def test_landmarks_are_found_again_from_another_view() -> None:
    scene = PlaneScene(seed=5)
    birth = look_at(np.array([0.0, 0.0, 1.3]), np.array([1.5, 0.3, 1.0]))
    lm = _map_from_view(scene, birth)
    view = look_at(np.array([0.25, -0.15, 1.25]), np.array([1.5, 0.45, 1.05]))
    img, _ = scene.render(view, INTR.K, (H, W))
    drifted = make_transform(np.eye(3), np.array([0.01, 0.005, 0.0])) @ view  # a few px off
    found = lm.search(img, drifted, INTR, 0, PARAMS)
    assert found.candidates >= 50
    assert len(found.ids) >= 0.5 * found.candidates
    truth = INTR.project((found.positions_world - view[:3, 3]) @ view[:3, :3])
    err = np.linalg.norm(found.pixels - truth, axis=1)
    assert np.median(err) < 0.15 and np.percentile(err, 95) < 0.5


def test_repeated_texture_gives_no_false_match() -> None:
    """On a texture that repeats every few pixels, a landmark could be matched one period off:
    the search keeps only matches with a unique peak, and what it keeps is right."""
    scene = PlaneScene(seed=5)
    rng = np.random.default_rng(0)
    tile = 128 + 60 * rng.standard_normal((3, 3)).astype(np.float32)
    scene.textures = [
        np.tile(np.kron(tile, np.ones((1, 1), np.float32)), (171, 171))[:512, :512]
    ] * len(scene.rects)
    birth = look_at(np.array([0.0, 0.0, 1.3]), np.array([1.5, 0.3, 1.0]))
    lm = _map_from_view(scene, birth)
    view = look_at(np.array([0.1, -0.05, 1.3]), np.array([1.5, 0.35, 1.0]))
    img, _ = scene.render(view, INTR.K, (H, W))
    drifted = make_transform(np.eye(3), np.array([0.02, 0.0, 0.0])) @ view
    found = lm.search(img, drifted, INTR, 0, PARAMS)
    assert found.candidates >= 50
    truth = INTR.project((found.positions_world - view[:3, 3]) @ view[:3, :3])
    err = np.linalg.norm(found.pixels - truth, axis=1)
    assert len(found.ids) < 0.2 * found.candidates
    assert (err < 1.0).all()


def test_smooth_texture_is_found_again_at_the_truth() -> None:
    """A smooth texture seen close (a broad NCC peak, as on the V1_01 room's walls): with
    ``unique_exclusion_px`` 4 the peak's own slopes are no rival peak, the landmarks are found
    again, where they are; with 2 (the default) most were dropped as not unique."""
    import cv2

    scene = PlaneScene(seed=5)
    scene.textures = [cv2.GaussianBlur(t, (0, 0), 6.0) for t in scene.textures]
    birth = look_at(np.array([0.0, 0.0, 1.3]), np.array([1.5, 0.3, 1.0]))
    view = look_at(np.array([0.1, -0.05, 1.3]), np.array([1.5, 0.35, 1.0]))
    img, _ = scene.render(view, INTR.K, (H, W))
    drifted = make_transform(np.eye(3), np.array([0.01, 0.005, 0.0])) @ view
    wide = dataclasses.replace(PARAMS, unique_exclusion_px=4)
    found = _map_from_view(scene, birth).search(img, drifted, INTR, 0, wide)
    assert found.candidates >= 50
    assert len(found.ids) >= 0.6 * found.candidates  # measured 77 of 108
    truth = INTR.project((found.positions_world - view[:3, 3]) @ view[:3, :3])
    err = np.linalg.norm(found.pixels - truth, axis=1)
    assert np.median(err) < 0.1 and np.percentile(err, 95) < 0.8
    narrow = _map_from_view(scene, birth).search(img, drifted, INTR, 0, PARAMS)
    assert len(narrow.ids) < 0.6 * len(found.ids)  # measured 41


def test_repeated_texture_is_still_rejected_with_a_wider_exclusion() -> None:
    """``unique_exclusion_px`` 4 keeps rejecting a texture that repeats every few pixels."""
    scene = PlaneScene(seed=5)
    rng = np.random.default_rng(0)
    tile = 128 + 60 * rng.standard_normal((3, 3)).astype(np.float32)
    scene.textures = [np.tile(tile, (171, 171))[:512, :512]] * len(scene.rects)
    birth = look_at(np.array([0.0, 0.0, 1.3]), np.array([1.5, 0.3, 1.0]))
    lm = _map_from_view(scene, birth)
    view = look_at(np.array([0.1, -0.05, 1.3]), np.array([1.5, 0.35, 1.0]))
    img, _ = scene.render(view, INTR.K, (H, W))
    drifted = make_transform(np.eye(3), np.array([0.02, 0.0, 0.0])) @ view
    found = lm.search(img, drifted, INTR, 0, dataclasses.replace(PARAMS, unique_exclusion_px=4))
    truth = INTR.project((found.positions_world - view[:3, 3]) @ view[:3, :3])
    err = np.linalg.norm(found.pixels - truth, axis=1)
    assert len(found.ids) < 0.2 * found.candidates
    assert (err < 1.0).all()

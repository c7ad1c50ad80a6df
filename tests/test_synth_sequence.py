"""The synthetic sequence: lazy frames, determinism, blackout, staying in the room, revisits,
scene mesh/surface samples, trajectories from files."""

from __future__ import annotations

import numpy as np
import pytest
from conftest import require

from datasets.euroc import read_trajectory_file
from datasets.rigs import euroc_like_calibration
from datasets.synth import make_synthetic_sequence
from datasets.synth.trajectories import PROFILES, make_profile
from slam.core.errors import InputError
from slam.core.geometry import matrix_to_quat_wxyz
from slam.core.messages import ImuSample, StereoFrame


@pytest.fixture(scope="module")
def seq():
    return make_synthetic_sequence("figure8", duration_s=6.0, seed=1, pixel_noise_std=1.5)


def test_sequence_layout(seq) -> None:
    calib = seq.calibration
    assert calib.is_stereo and calib.imu is not None
    assert abs(calib.stereo_baseline_m() - 0.11) < 0.005
    assert seq.num_frames == 121 and seq.num_imu == 1201
    assert np.all(np.diff(seq.frame_times_ns()) == 50_000_000)
    assert np.all(np.diff(seq.imu().t_ns) == 5_000_000)
    assert len(seq.ground_truth) == seq.num_imu
    f = seq.frame(60)
    assert isinstance(f, StereoFrame) and f.index == 60 and f.t_ns == 3_000_000_000
    assert f.left.shape == (480, 752) and f.left.dtype == np.uint8 and f.right is not None
    assert f.left.std() > 20  # textured
    short = make_synthetic_sequence("figure8", duration_s=0.5)
    msgs = list(short.messages())
    assert sum(isinstance(m, ImuSample) for m in msgs) == short.num_imu == 101
    assert sum(isinstance(m, StereoFrame) for m in msgs) == short.num_frames == 11
    assert all(a.t_ns <= b.t_ns for a, b in zip(msgs, msgs[1:]))


def test_frames_and_noise_are_deterministic_by_seed(seq) -> None:
    again = make_synthetic_sequence("figure8", duration_s=6.0, seed=1, pixel_noise_std=1.5)
    other = make_synthetic_sequence("figure8", duration_s=6.0, seed=2, pixel_noise_std=1.5)
    a, b, c = seq.frame(40), again.frame(40), other.frame(40)
    assert np.array_equal(a.left, b.left) and np.array_equal(a.right, b.right)
    assert not np.array_equal(a.left, c.left)  # different pixel noise
    assert np.array_equal(seq.imu().accel_m_s2, again.imu().accel_m_s2)
    assert not np.array_equal(seq.imu().accel_m_s2, other.imu().accel_m_s2)
    # the scene itself does not depend on the noise seed
    assert np.abs(a.left.astype(int) - c.left.astype(int)).mean() < 3.0


def test_ground_truth_matches_render_pose_and_depth(seq) -> None:
    gt = seq.ground_truth
    i = 50
    t = seq.frame_times_ns()[i]
    k = int(np.searchsorted(gt.t_ns, t))
    assert gt.t_ns[k] == t
    pose = seq.world_from_body_at(int(t))
    assert np.allclose(gt.positions_m[k], pose[:3, 3])
    assert np.allclose(gt.q_wxyz[k], matrix_to_quat_wxyz(pose[:3, :3]))
    depth = seq.depth(i)
    assert depth.shape == (480, 752) and depth.dtype == np.float32
    assert 0.3 < depth.min() and depth.max() < 12.0


def test_blackout_frames_are_black() -> None:
    s = make_synthetic_sequence("figure8", duration_s=5.0, blackout=(2.0, 1.0), imu_noise=False)
    black = [i for i in range(s.num_frames) if s.is_blacked_out(i)]
    assert len(black) == 20
    assert s.frame(black[0]).left.max() == 0 and s.frame(black[-1]).right.max() == 0
    assert s.frame(black[-1] + 1).left.max() > 0 and s.frame(black[0] - 1).left.max() > 0
    assert s.num_imu == 1001  # IMU continues


@pytest.mark.parametrize("profile", PROFILES)
@pytest.mark.parametrize("moving_start", [False, True])
def test_cameras_stay_inside_room_and_out_of_boxes(profile: str, moving_start: bool) -> None:
    motion = make_profile(profile, moving_start=moving_start)
    calib = euroc_like_calibration()
    t = np.arange(0.0, max(motion.default_duration_s, 150.0), 0.05)
    poses = motion.sample(t).world_from_body()
    s = make_synthetic_sequence(profile, duration_s=1.0, moving_start=moving_start)
    scene = s.scene
    assert len(scene.boxes) >= 3, "the scene needs boxes for parallax"
    for cam in calib.cameras:
        centres = poses[:, :3, :3] @ cam.body_from_cam[:3, 3] + poses[:, :3, 3]
        assert scene.clearance_m(centres).min() > 0.5


def test_loop_revisits_its_start() -> None:
    motion = make_profile("loop")
    start, back = motion.sample(np.array([0.0, 78.0])).world_from_body()
    assert np.allclose(start, back, atol=1e-9)
    mid = motion.sample(np.array([40.0])).world_from_body()[0]
    assert np.linalg.norm(mid[:3, 3] - start[:3, 3]) > 2.0


def test_scene_mesh_and_surface_samples(seq) -> None:
    verts, tris = seq.scene_mesh()
    assert verts.shape[1] == 3 and tris.shape[1] == 3 and tris.max() < len(verts)
    # total area of the mesh equals the visible surface area
    e1 = verts[tris[:, 1]] - verts[tris[:, 0]]
    e2 = verts[tris[:, 2]] - verts[tris[:, 0]]
    area = 0.5 * np.linalg.norm(np.cross(e1, e2), axis=1).sum()
    assert np.isclose(area, sum(f.area_m2 for f in seq.scene.surface_faces()))
    pts = seq.sample_surface_points(1000, seed=0)
    assert pts.shape == (1000, 3)
    on_some_face = np.zeros(1000, bool)
    for f in seq.scene.surface_faces():
        on_some_face |= np.abs(pts[:, f.axis] - f.plane_m) < 1e-9
    assert on_some_face.all()


def test_aliasing_scene_repeats_textures() -> None:
    s = make_synthetic_sequence("loop", duration_s=1.0, aliasing=True)
    faces = s.scene.faces
    box_faces = [f for f in faces if f.owner >= 0 and f.axis == 0 and f.side == 1]
    assert len(box_faces) >= 2
    assert len({(f.atlas_x0, f.atlas_y0) for f in box_faces}) == 1
    normal = make_synthetic_sequence("loop", duration_s=1.0)
    nf = [f for f in normal.scene.faces if f.owner >= 0 and f.axis == 0 and f.side == 1]
    assert len({(f.atlas_x0, f.atlas_y0) for f in nf}) == len(nf)


def test_trajectory_from_tum_file_reproduces_the_motion(tmp_path) -> None:
    ref = make_synthetic_sequence("figure8", duration_s=12.0, imu_noise=False)
    gt = ref.ground_truth.slice(slice(0, None, 4))  # 50 Hz poses
    path = tmp_path / "gt.tum"
    q = gt.q_wxyz
    rows = [
        f"{t * 1e-9:.9f} {p[0]:.9f} {p[1]:.9f} {p[2]:.9f} {qq[1]:.9f} {qq[2]:.9f} {qq[3]:.9f} {qq[0]:.9f}"
        for t, p, qq in zip(gt.t_ns, gt.positions_m, q)
    ]
    path.write_text("# t x y z qx qy qz qw\n" + "\n".join(rows) + "\n")
    assert len(read_trajectory_file(path)) == len(gt)
    s = make_synthetic_sequence(trajectory_file=str(path), imu_noise=False)
    assert s.num_frames == 240 or s.num_frames == 241
    mid = slice(200, 2000)
    assert np.abs(s.ground_truth.positions_m[mid] - ref.ground_truth.positions_m[mid]).max() < 1e-3
    gyro_err = np.abs(s.imu().gyro_rad_s[mid] - ref.imu().gyro_rad_s[mid]).max()
    acc_err = np.abs(s.imu().accel_m_s2[mid] - ref.imu().accel_m_s2[mid]).max()
    assert gyro_err < 0.02 and acc_err < 0.2
    assert s.frame(100).left.std() > 20


def test_euroc_ground_truth_with_real_imu(shared_data) -> None:
    root = require(shared_data / "euroc_v101_micro")
    gt_csv = require(root / "groundtruth_openvins" / "V1_01_easy.csv")
    imu_csv = require(root / "mav0" / "imu0" / "data.csv")
    s = make_synthetic_sequence(trajectory_file=str(gt_csv), imu_csv=str(imu_csv), duration_s=5.0)
    t_gt = read_trajectory_file(gt_csv).t_ns
    assert s.frame_times_ns()[0] == t_gt[0]
    assert 990 <= s.num_imu <= 1002  # real 200 Hz IMU over 5 s
    assert s.imu().accel_m_s2[:, 0].mean() > 8.0  # the real sensor's gravity axis
    f = s.frame(10)
    assert f.left.std() > 20
    centres = s.ground_truth.positions_m
    assert s.scene.clearance_m(centres).min() > 1.0


def test_bad_inputs_raise_input_error(tmp_path) -> None:
    with pytest.raises(InputError):
        make_synthetic_sequence("nope")
    with pytest.raises(InputError):
        make_synthetic_sequence(trajectory_file=str(tmp_path / "missing.txt"))
    bad = tmp_path / "bad.txt"
    bad.write_text("1 2 3\n")
    with pytest.raises(InputError):
        make_synthetic_sequence(trajectory_file=str(bad))


def _predict(seq, index_from: int, cam_from: int, index_to: int, cam_to: int, px: np.ndarray):
    """Where integer pixels of one image land in another, from true depth and poses."""
    from datasets.synth.render import pixel_rays

    rays = pixel_rays(seq.calibration.cameras[cam_from].intrinsics)
    z = seq.depth(index_from, cam_from)[px[:, 1], px[:, 0]]
    p_cam = np.concatenate([rays[px[:, 1], px[:, 0]], np.ones((len(px), 1))], 1) * z[:, None]
    a = seq.world_from_cam(index_from, cam_from)
    b = seq.world_from_cam(index_to, cam_to)
    p_world = p_cam @ a[:3, :3].T + a[:3, 3]
    p_to = (p_world - b[:3, 3]) @ b[:3, :3]
    return seq.calibration.cameras[cam_to].intrinsics.project(p_to)


def test_klt_flow_and_stereo_match_ground_truth(seq) -> None:
    """End to end: features tracked by KLT (temporal and left->right) land where the true depth,
    poses and calibration predict, to a small fraction of a pixel."""
    import cv2

    i = 70
    f0, f1 = seq.frame(i), seq.frame(i + 1)
    corners = cv2.goodFeaturesToTrack(f0.left, 300, 0.01, 12)[:, 0]
    px = np.round(corners).astype(int)
    px = px[(px[:, 0] > 20) & (px[:, 0] < 731) & (px[:, 1] > 20) & (px[:, 1] < 459)]
    start = px.astype(np.float32).reshape(-1, 1, 2)
    for target, cam_to, index_to in ((f1.left, 0, i + 1), (f0.right, 1, i)):
        tracked, status, _ = cv2.calcOpticalFlowPyrLK(
            f0.left, target, start, None, winSize=(21, 21), maxLevel=3
        )
        ok = status[:, 0] == 1
        expected = _predict(seq, i, 0, index_to, cam_to, px)
        err = np.linalg.norm(tracked[:, 0] - expected, axis=1)[ok]
        inside = (expected[ok, 0] > 10) & (expected[ok, 0] < 742)
        assert ok.mean() > 0.8
        assert np.median(err[inside]) < 0.1, (cam_to, np.median(err[inside]))


def test_prefetching_iter_frames_matches_random_access() -> None:
    s = make_synthetic_sequence("aggressive", duration_s=0.4, seed=2, pixel_noise_std=1.0)
    frames = list(s.iter_frames())
    assert [f.index for f in frames] == list(range(s.num_frames))
    for f in frames[::3]:
        g = s.frame(f.index)
        assert np.array_equal(f.left, g.left) and np.array_equal(f.right, g.right)
    it = s.iter_frames()
    assert next(it).index == 0
    it.close()  # abandoning the iterator early must not hang

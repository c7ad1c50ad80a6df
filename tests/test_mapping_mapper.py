"""The dense mapper on a synthetic room: fused-mesh accuracy/completion and loop re-integration."""

from __future__ import annotations

import pickle

import numpy as np
import pytest
from scipy.spatial import cKDTree
from synthetic_planes import PlaneScene, orbit_poses

from mapping.mapper import DenseMapper, MapperConfig, StereoRig
from mapping.planesweep import SweepConfig, Undistorter
from mapping.tsdf import TsdfConfig
from slam.core.calibration import CameraIntrinsics

W, H = 320, 240
K = np.array([[230.0, 0.0, 160.0], [0.0, 230.0, 120.0], [0.0, 0.0, 1.0]])
CAM1_FROM_CAM0 = np.eye(4)
CAM1_FROM_CAM0[0, 3] = -0.11  # right camera 11 cm to the right of the left one


def make_mapper(
    num_planes: int = 96, depth_scale: float = 1.0, depth_method: str = "sweep"
) -> DenseMapper:
    intr = CameraIntrinsics(W, H, 230.0, 230.0, 160.0, 120.0)
    rig = StereoRig(Undistorter(intr), Undistorter(intr), K, K, CAM1_FROM_CAM0)
    cfg = MapperConfig(
        tsdf=TsdfConfig(voxel_m=0.02, max_depth_m=4.0),
        sweep=SweepConfig(depth_min_m=0.5, depth_max_m=6.0, num_planes=num_planes),
        depth_scale=depth_scale,
        depth_method=depth_method,
    )
    return DenseMapper(cfg, rig)


@pytest.fixture(scope="module")
def room():
    scene = PlaneScene()
    poses = orbit_poses(16)
    frames = []
    for pose in poses:
        img, depth = scene.render(pose, K, (H, W))
        right, _ = scene.render(pose @ np.linalg.inv(CAM1_FROM_CAM0), K, (H, W))
        frames.append((pose, img, right, depth))
    return scene, frames


def visible_surface_samples(scene, frames, n=20000):
    """True-surface samples seen (unoccluded, within 4 m) by at least one keyframe."""
    pts = scene.sample_surface_points(n, np.random.default_rng(0))
    vis = np.zeros(len(pts), bool)
    for pose, _, _, depth in frames:
        cw = np.linalg.inv(pose)
        pc = pts @ cw[:3, :3].T + cw[:3, 3]
        z = pc[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            u = np.round(K[0, 0] * pc[:, 0] / z + K[0, 2])
            v = np.round(K[1, 1] * pc[:, 1] / z + K[1, 2])
        ok = (z > 0.1) & (u >= 0) & (u < W) & (v >= 0) & (v < H)
        d = np.zeros(len(pts))
        d[ok] = depth[v[ok].astype(int), u[ok].astype(int)]
        vis |= ok & (np.abs(d - z) < 0.03) & (z < 4.0)
    return pts[vis]


def accuracy_completion(scene, frames, mesh):
    acc = scene.distance_to_surface(mesh.vertices_m.astype(float)).mean()
    samples = visible_surface_samples(scene, frames)
    dist, _ = cKDTree(mesh.vertices_m).query(samples)
    return acc, float(np.mean(dist < 0.05))


@pytest.mark.parametrize(
    ("depth_method", "depth_scale"), [("sweep", 1.0), ("sweep", 0.5), ("sgbm", 1.0)]
)
def test_stereo_fusion_meets_accuracy_and_completion(room, depth_method, depth_scale):
    scene, frames = room
    mapper = make_mapper(depth_scale=depth_scale, depth_method=depth_method)
    for i, (pose, img, right, _) in enumerate(frames):
        rep = mapper.add_keyframe(i * 100_000_000, img, right, pose)
        assert rep.num_sources >= 1
    acc, comp = accuracy_completion(scene, frames, mapper.mesh())
    assert acc <= 0.02, acc  # mean vertex-to-surface distance (m)
    assert comp >= 0.90, comp  # true surface within 5 cm of the mesh


def test_update_poses_reintegrates_to_the_corrected_map(room):
    scene, frames = room
    rng = np.random.default_rng(5)
    mapper = make_mapper()
    for i, (pose, img, _, depth) in enumerate(frames):
        wrong = pose.copy()
        wrong[:3, 3] += rng.normal(scale=0.05, size=3)  # drifted poses
        mapper.add_keyframe(i, img, None, wrong, depth_m=depth)
    acc_before, _ = accuracy_completion(scene, frames, mapper.mesh(0.0))
    moved = mapper.update_poses({i: f[0] for i, f in enumerate(frames)})
    assert moved == len(frames)
    acc_after, comp_after = accuracy_completion(scene, frames, mapper.mesh(0.0))
    assert acc_before > 0.01
    assert acc_after < 0.003 and comp_after > 0.97, (acc_after, comp_after)
    assert mapper.update_poses({i: f[0] for i, f in enumerate(frames)}) == 0  # nothing moved


@pytest.mark.parametrize("depth_method", ["sweep", "sgbm"])
def test_mapper_pickles_for_a_worker_process(room, depth_method):
    _, frames = room
    mapper = make_mapper(num_planes=16, depth_method=depth_method)
    pose, img, right, _ = frames[0]
    mapper.add_keyframe(0, img, right, pose)
    clone = pickle.loads(pickle.dumps(mapper))
    assert clone.volume.num_blocks == mapper.volume.num_blocks
    assert clone.mesh().num_faces == mapper.mesh().num_faces
    pose, img, right, _ = frames[1]  # the clone still computes depth
    assert clone.add_keyframe(1, img, right, pose).valid_fraction > 0.3


def test_mesh_threshold_needs_multi_view_support(room):
    """One fused keyframe meshes every observed surface; from mesh_min_weight_keyframes on, the
    multi-view weight threshold applies (it removes single-view floaters)."""
    scene, frames = room
    mapper = make_mapper()
    pose, img, right, _ = frames[0]
    mapper.add_keyframe(0, img, right, pose)
    assert mapper.mesh().num_vertices == mapper.mesh(0.0).num_vertices > 0
    for i, (pose, img, right, _) in enumerate(frames[1:4], start=1):
        mapper.add_keyframe(i * 100_000_000, img, right, pose)
    assert mapper.num_keyframes >= mapper.config.mesh_min_weight_keyframes
    thresholded = mapper.mesh(mapper.config.mesh_min_weight).num_vertices
    assert mapper.mesh().num_vertices == thresholded < mapper.mesh(0.0).num_vertices


def test_small_mesh_components_are_removed():
    """Two separate pieces: a 10x10-vertex grid and a 2-triangle speck; the speck goes, the
    grid stays with its faces re-indexed onto the same coordinates."""
    from mapping.mesh import TriangleMesh, remove_small_components

    g = np.stack(np.meshgrid(np.arange(10.0), np.arange(10.0), indexing="ij"), -1).reshape(-1, 2)
    grid = np.c_[g, np.zeros(len(g))]
    idx = np.arange(100).reshape(10, 10)
    a, b, c, d = (
        idx[:-1, :-1].ravel(),
        idx[1:, :-1].ravel(),
        idx[:-1, 1:].ravel(),
        idx[1:, 1:].ravel(),
    )
    grid_faces = np.r_[np.c_[a, b, d], np.c_[a, d, c]]
    speck = np.array([[50.0, 0, 0], [51, 0, 0], [50, 1, 0], [51, 1, 0]])
    verts = np.r_[speck, grid].astype(np.float32)  # the speck first: indices must shift
    faces = np.r_[[[0, 1, 3], [0, 3, 2]], grid_faces + 4].astype(np.int32)
    mesh = TriangleMesh(verts, faces, np.tile([0, 0, 1.0], (104, 1)).astype(np.float32),
                        np.arange(104 * 3).reshape(104, 3).astype(np.uint8))  # fmt: skip
    out = remove_small_components(mesh, 5)
    assert out.num_vertices == 100 and out.num_faces == len(grid_faces)
    np.testing.assert_array_equal(out.vertices_m[out.faces], verts[faces[2:]])
    np.testing.assert_array_equal(out.colors_rgb, mesh.colors_rgb[4:])
    assert remove_small_components(mesh, 0) is mesh

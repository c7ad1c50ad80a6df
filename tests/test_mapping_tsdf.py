"""TSDF fusion, marching cubes and PLY I/O: analytic scenes with exact surfaces, and 7-Scenes."""

from __future__ import annotations

import numpy as np
import pytest
from conftest import require

from datasets.ply import read_ply, write_ply_mesh, write_ply_points
from mapping.mesh import extract_mesh
from mapping.render import look_at
from mapping.tsdf import TsdfConfig, TsdfVolume, pack_block_keys, unpack_block_keys

K = np.array([[300.0, 0.0, 160.0], [0.0, 300.0, 120.0], [0.0, 0.0, 1.0]])
SPHERE_C = np.array([0.0, 0.0, 2.0])
SPHERE_R = 0.5


def sphere_depth(world_from_cam: np.ndarray, hw: tuple[int, int] = (240, 320)) -> np.ndarray:
    """Exact depth (z along the optical axis) of a sphere, 0 where the ray misses it."""
    h, w = hw
    v, u = np.mgrid[0:h, 0:w].astype(float)
    rays_c = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)], -1)
    rays_w = rays_c @ world_from_cam[:3, :3].T
    o = world_from_cam[:3, 3]
    oc = o - SPHERE_C
    a = np.sum(rays_w**2, -1)
    b = 2 * rays_w @ oc
    c = oc @ oc - SPHERE_R**2
    disc = b * b - 4 * a * c
    t = (-b - np.sqrt(np.maximum(disc, 0))) / (2 * a)  # ray parameter = z in the camera
    return np.where(disc > 0, t, 0.0).astype(np.float32)


def orbit_poses(n: int) -> list[np.ndarray]:
    out = []
    for ang in np.linspace(0, 2 * np.pi, n, endpoint=False):
        eye = SPHERE_C + 1.5 * np.array([np.sin(ang), 0.3, -np.cos(ang)])
        out.append(look_at(eye, SPHERE_C, np.array([0.0, -1.0, 0.0])))
    return out


def test_block_keys_roundtrip():
    xyz = np.array([[0, 0, 0], [-1, 2, -3], [1000, -1000, 77]])
    np.testing.assert_array_equal(unpack_block_keys(pack_block_keys(xyz)), xyz)


def test_sphere_fusion_accuracy_and_completion():
    vol = TsdfVolume(TsdfConfig(voxel_m=0.02))
    for pose in orbit_poses(12):
        vol.integrate(sphere_depth(pose), K, pose)
    mesh = extract_mesh(vol)
    dist = np.abs(np.linalg.norm(mesh.vertices_m - SPHERE_C, axis=1) - SPHERE_R)
    assert mesh.num_faces > 1000
    assert dist.mean() < 0.005, dist.mean()  # quarter of a voxel
    # Normals point out of the sphere (towards the free space the cameras saw).
    radial = (mesh.vertices_m - SPHERE_C) / np.linalg.norm(mesh.vertices_m - SPHERE_C, axis=1)[
        :, None
    ]
    assert np.mean(np.sum(radial * mesh.normals, axis=1) > 0.9) > 0.95
    # Completion over the band the orbit sees (|y - c_y| < 0.3 m).
    rng = np.random.default_rng(0)
    s = rng.normal(size=(4000, 3))
    s = SPHERE_C + SPHERE_R * s / np.linalg.norm(s, axis=1, keepdims=True)
    s = s[np.abs(s[:, 1] - SPHERE_C[1]) < 0.3]
    from scipy.spatial import cKDTree

    d, _ = cKDTree(mesh.vertices_m).query(s)
    assert np.mean(d < 0.02) > 0.97


def test_deintegrate_is_exact_inverse():
    poses = orbit_poses(4)
    vol = TsdfVolume(TsdfConfig(voxel_m=0.03))
    vol.integrate(sphere_depth(poses[0]), K, poses[0])
    vol.integrate(sphere_depth(poses[1]), K, poses[1])
    n = vol.num_blocks
    t_before, w_before = vol.tsdf[:n].copy(), vol.weight[:n].copy()
    vol.integrate(sphere_depth(poses[2]), K, poses[2])
    vol.deintegrate(sphere_depth(poses[2]), K, poses[2])
    np.testing.assert_allclose(vol.weight[:n], w_before, atol=1e-6)
    seen = w_before > 0
    np.testing.assert_allclose(vol.tsdf[:n][seen], t_before[seen], atol=1e-5)
    assert np.all(vol.weight[n : vol.num_blocks] == 0)  # blocks new to pose 2 are empty again


def test_ply_roundtrip(tmp_path):
    rng = np.random.default_rng(1)
    v = rng.normal(size=(50, 3)).astype(np.float32)
    f = rng.integers(0, 50, size=(80, 3))
    n = rng.normal(size=(50, 3)).astype(np.float32)
    c = rng.integers(0, 256, size=(50, 3)).astype(np.uint8)
    path = write_ply_mesh(tmp_path / "m.ply", v, f, n, c)
    ply = read_ply(path)
    assert "element vertex 50" in ply.header and "element face 80" in ply.header
    assert "binary_little_endian" in ply.header
    np.testing.assert_array_equal(ply.points, v)
    np.testing.assert_array_equal(ply.faces, f)
    np.testing.assert_array_equal(ply.vertex["nx"], n[:, 0])
    np.testing.assert_array_equal(ply.vertex["blue"], c[:, 2])
    ply2 = read_ply(write_ply_points(tmp_path / "p.ply", v, c))
    assert ply2.faces is None and len(ply2.points) == 50
    assert not list(tmp_path.glob(".*tmp"))  # atomic write left nothing behind


def test_seven_scenes_fusion_gives_a_closed_looking_mesh(shared_data):
    from datasets.rgbd_folder import RgbdFolder

    folder = RgbdFolder(require(shared_data / "7scenes_rgbd_400"))
    vol = TsdfVolume(TsdfConfig(voxel_m=0.04))
    centres = []
    for i in range(0, 400, 20):
        fr = folder.frame(i)
        vol.integrate(fr.depth_m, folder.K, fr.world_from_cam, fr.color_rgb)
        centres.append(fr.world_from_cam[:3, 3])
    mesh = extract_mesh(vol)
    lo, hi = mesh.bounds()
    extent = hi - lo
    assert mesh.num_vertices > 5000
    assert np.all(extent > 1.0) and np.all(extent < 8.0), extent  # a room-sized scene
    # Mostly one piece: the merged mesh has few boundary edges relative to its size.
    f = mesh.faces.astype(np.int64)
    edges = np.sort(np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]]), axis=1)
    _, counts = np.unique(edges[:, 0] * mesh.num_vertices + edges[:, 1], return_counts=True)
    assert np.mean(counts == 1) < 0.12  # boundary edges (the scan's rim and small fragments)
    assert np.all(counts <= 2)  # manifold edges
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    n = mesh.num_vertices
    adj = coo_matrix((np.ones(len(edges)), (edges[:, 0], edges[:, 1])), shape=(n, n))
    _, label = connected_components(adj, directed=False)
    assert np.bincount(label).max() > 0.7 * n  # one dominant piece
    # Normals face the cameras that saw them (free space is on the camera side).
    c = np.mean(centres, axis=0)
    assert np.mean(np.sum(mesh.normals * (c - mesh.vertices_m), axis=1) > 0) > 0.75
    assert mesh.colors_rgb is not None and mesh.colors_rgb.mean() > 30


@pytest.mark.parametrize("voxel", [0.05])
def test_empty_volume_gives_empty_mesh(voxel):
    assert extract_mesh(TsdfVolume(TsdfConfig(voxel_m=voxel))).num_faces == 0

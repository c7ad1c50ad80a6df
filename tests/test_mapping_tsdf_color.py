"""TSDF colour and weight arithmetic: integrate, de-integrate and re-integrate against known
surface colours, zero-weight voxels, and meshes without black vertices. Both update loops
(numpy, and numba when installed) are checked, and against each other."""

from __future__ import annotations

import numpy as np
import pytest
from test_mapping_tsdf import SPHERE_C, SPHERE_R, K, orbit_poses, sphere_depth

from mapping.mesh import extract_mesh
from mapping.tsdf import MIN_WEIGHT, TsdfConfig, TsdfVolume, numba_available

KERNELS = [
    "numpy",
    pytest.param(
        "numba",
        marks=pytest.mark.skipif(
            not numba_available(), reason="numba not installed (the 'fast' extra)"
        ),
    ),
]


def surface_color(p_world: np.ndarray) -> np.ndarray:
    """Known colour of the sphere at world points (N, 3): four quadrants, no black anywhere."""
    rel = p_world - SPHERE_C
    r = np.where(rel[:, 0] > 0, 220.0, 60.0)
    g = np.where(rel[:, 1] > 0, 200.0, 40.0)
    b = np.full(len(p_world), 120.0)
    return np.stack([r, g, b], axis=1)


def color_image(world_from_cam: np.ndarray, depth: np.ndarray) -> np.ndarray:
    """The colour image a camera sees of the sphere (uint8 RGB, black where it misses)."""
    h, w = depth.shape
    v, u = np.mgrid[0:h, 0:w].astype(float)
    p_cam = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)], -1)
    p_cam *= depth[..., None]
    p_world = p_cam.reshape(-1, 3) @ world_from_cam[:3, :3].T + world_from_cam[:3, 3]
    img = surface_color(p_world).reshape(h, w, 3)
    img[depth <= 0] = 0
    return img.astype(np.uint8)


def view(pose: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    depth = sphere_depth(pose)
    return depth, color_image(pose, depth)


def colour_error_away_from_seams(vol: TsdfVolume) -> tuple[np.ndarray, int]:
    """Per-voxel |colour - known| (max over channels) of the coloured surface voxels that lie
    more than 4 cm from a quadrant seam (each voxel's colour mixes pixels of its footprint)."""
    pts, cols = vol.surface_points(max_abs_tsdf=0.3)
    n = vol.num_blocks
    near = (vol.weight[:n] > 0) & (np.abs(vol.tsdf[:n]) < 0.3)
    has = vol.color_weight[:n][near] > 0
    rel = pts - SPHERE_C
    away = (np.abs(rel[:, 0]) > 0.04) & (np.abs(rel[:, 1]) > 0.04) & has
    err = np.abs(cols[away].astype(float) - surface_color(pts[away])).max(axis=1)
    return err, int(away.sum())


@pytest.mark.parametrize("kernel", KERNELS)
def test_integrate_deintegrate_reintegrate_keeps_known_colours(kernel):
    poses = orbit_poses(6)[:3]
    vol = TsdfVolume(TsdfConfig(voxel_m=0.02, kernel=kernel))
    views = [view(p) for p in poses]
    for (d, c), p in zip(views, poses):
        vol.integrate(d, K, p, c)
    err, n = colour_error_away_from_seams(vol)
    assert n > 500
    assert np.percentile(err, 99) <= 2, np.percentile(err, 99)
    # Remove every view: no weight, no colour weight left, nothing black-but-observed.
    for (d, c), p in zip(views, poses):
        vol.deintegrate(d, K, p, c)
    nb = vol.num_blocks
    assert np.all(vol.weight[:nb] == 0) and np.all(vol.color_weight[:nb] == 0)
    assert np.all(vol.tsdf[:nb] == 1.0) and np.all(vol.color_x256[:nb] == 0)
    assert np.all(np.isfinite(vol.tsdf[:nb]))
    assert extract_mesh(vol).num_vertices == 0
    # Re-integrate two of them: the colours are the known ones again.
    for (d, c), p in list(zip(views, poses))[:2]:
        vol.integrate(d, K, p, c)
    err, n = colour_error_away_from_seams(vol)
    assert n > 300
    assert np.percentile(err, 99) <= 2, np.percentile(err, 99)


@pytest.mark.parametrize("kernel", KERNELS)
def test_deintegrating_one_of_two_views_leaves_the_others_colour(kernel):
    """The voxels two views share keep the colour of the one left (not black, not a blend)."""
    p0, p1 = orbit_poses(8)[:2]
    vol = TsdfVolume(TsdfConfig(voxel_m=0.02, kernel=kernel))
    (d0, c0), (d1, c1) = view(p0), view(p1)
    # Weights as the mapper's depth-uncertainty map: far pixels weigh less (not 1).
    w0 = np.minimum(1.0, (1.2 / np.maximum(d0, 1e-3)) ** 2).astype(np.float32)
    w1 = np.minimum(1.0, (1.2 / np.maximum(d1, 1e-3)) ** 2).astype(np.float32)
    vol.integrate(d0, K, p0, c0, weight_map=w0)
    vol.integrate(d1, K, p1, np.full_like(c1, 250), weight_map=w1)  # a wrong colour, removed
    vol.deintegrate(d1, K, p1, np.full_like(c1, 250), weight_map=w1)
    err, n = colour_error_away_from_seams(vol)
    assert n > 300
    assert np.percentile(err, 99) <= 2, np.percentile(err, 99)
    nb = vol.num_blocks
    w = vol.weight[:nb]
    assert np.all((w == 0) | (w > MIN_WEIGHT))  # no voxel left with a crumb of weight
    cw = vol.color_weight[:nb]
    assert np.all(vol.color_x256[:nb][cw == 0] == 0)


@pytest.mark.parametrize("kernel", KERNELS)
def test_weights_that_round_to_a_crumb_reset_the_voxel(kernel):
    """0.1 + 0.2 - 0.1 - 0.2 is not 0 in float32: such voxels must become unobserved, not
    divide by ~1e-8 (which sent tsdf and colour to their clip limits)."""
    pose = orbit_poses(4)[0]
    d, c = view(pose)
    vol = TsdfVolume(TsdfConfig(voxel_m=0.02, kernel=kernel))
    for wgt in (0.1, 0.2, 0.7):
        vol.integrate(d, K, pose, c, weight=wgt)
    for wgt in (0.1, 0.2, 0.7):
        vol.integrate(d, K, pose, c, weight=-wgt)
    nb = vol.num_blocks
    assert np.all(vol.weight[:nb] == 0), vol.weight[:nb].max()
    assert np.all(vol.tsdf[:nb] == 1.0)
    assert np.all(vol.color_weight[:nb] == 0) and np.all(vol.color_x256[:nb] == 0)


@pytest.mark.parametrize("kernel", KERNELS)
def test_mesh_has_no_black_vertices_where_the_scene_has_none(kernel):
    """Geometry fused without colour (the mapper's re-integration keeps no images by default)
    must not come out black: such vertices take their coloured neighbours' colour."""
    poses = orbit_poses(12)
    vol = TsdfVolume(TsdfConfig(voxel_m=0.02, kernel=kernel))
    for p in poses[:4]:
        d, c = view(p)
        vol.integrate(d, K, p, c)
    for p in poses[4:8]:  # more of the sphere, geometry only
        vol.integrate(sphere_depth(p), K, p)
    mesh = extract_mesh(vol)
    assert mesh.num_vertices > 1000 and mesh.colors_rgb is not None
    black = np.all(mesh.colors_rgb < 20, axis=1)
    assert black.sum() == 0, f"{black.mean():.1%} black vertices"
    # Where colour was fused, the vertex colours are the known ones.
    dist = np.abs(np.linalg.norm(mesh.vertices_m - SPHERE_C, axis=1) - SPHERE_R)
    assert dist.mean() < 0.01
    lit = np.zeros(len(mesh.vertices_m), bool)
    for p in poses[:4]:
        d = np.linalg.norm(mesh.vertices_m - p[:3, 3], axis=1)
        lit |= d < np.linalg.norm(SPHERE_C - p[:3, 3])  # the side facing a coloured view
    rel = mesh.vertices_m - SPHERE_C
    away = lit & (np.abs(rel[:, 0]) > 0.05) & (np.abs(rel[:, 1]) > 0.05)
    err = np.abs(mesh.colors_rgb[away].astype(float) - surface_color(mesh.vertices_m[away]))
    assert away.sum() > 200
    assert np.median(err.max(axis=1)) <= 2


@pytest.mark.skipif(not numba_available(), reason="numba not installed (the 'fast' extra)")
def test_numba_and_numpy_update_loops_agree_bit_for_bit():
    """Integrate (with and without per-pixel weights and colour), de-integrate, re-integrate:
    the compiled loop (one and two threads) gives the numpy loop's volume exactly."""
    poses = orbit_poses(5)
    vols = {
        "numpy": TsdfVolume(TsdfConfig(voxel_m=0.02, kernel="numpy")),
        "numba": TsdfVolume(TsdfConfig(voxel_m=0.02, kernel="numba")),
        "numba2": TsdfVolume(TsdfConfig(voxel_m=0.02, kernel="numba", threads=2)),
    }
    views = [view(p) for p in poses]
    wmaps = [np.minimum(1.0, (1.2 / np.maximum(d, 1e-3)) ** 2).astype(np.float32) for d, _ in views]
    for i, ((d, c), p) in enumerate(zip(views, poses)):
        for v in vols.values():
            if i % 2:
                v.integrate(d, K, p, c, weight_map=wmaps[i])
            else:
                v.integrate(d, K, p, None if i == 2 else c, weight=0.7)
    (d, c), p = views[1], poses[1]
    for v in vols.values():
        v.deintegrate(d, K, p, c, weight_map=wmaps[1])  # and back again: re-integrated
    for v in vols.values():
        v.integrate(d, K, p @ _small_motion(), c, weight_map=wmaps[1])
    a = vols["numpy"]
    n = a.num_blocks
    assert n > 100 and a.observed_voxel_count() > 10_000
    for name in ("numba", "numba2"):
        b = vols[name]
        assert b.kernel == "numba" and b.num_blocks == n
        np.testing.assert_array_equal(a.block_coords(), b.block_coords())
        for field in ("tsdf", "weight", "color_x256", "color_weight"):
            np.testing.assert_array_equal(getattr(a, field)[:n], getattr(b, field)[:n], field)


def _small_motion() -> np.ndarray:
    """A 2 cm, 1 degree pose change (as a loop correction moves a keyframe)."""
    c, s = np.cos(np.radians(1.0)), np.sin(np.radians(1.0))
    t = np.eye(4)
    t[:3, :3] = [[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]
    t[:3, 3] = [0.02, 0.0, 0.0]
    return t

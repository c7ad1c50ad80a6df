"""Renderer geometry: markers land where the calibration projects them; depth is the ray-plane
distance; pixel rays invert the distortion model."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from datasets.rigs import euroc_like_calibration
from datasets.synth.render import CameraRenderer, StereoRenderer, pixel_rays
from datasets.synth.scene import Scene, build_scene
from datasets.synth.trajectories import NOMINAL_FROM_BODY
from slam.core.geometry import invert_transform, make_transform, transform_points


def _body_pose(position: np.ndarray, yaw: float, pitch: float, roll: float) -> np.ndarray:
    rot = Rotation.from_euler("ZYX", [yaw, pitch, roll]).as_matrix() @ NOMINAL_FROM_BODY
    return make_transform(rot, position)


MARKERS = [(4.0, 0.6, 1.9), (4.0, -0.8, 1.2), (1.3, 3.0, 1.4), (2.5, -1.2, 0.0)]


@pytest.fixture(scope="module")
def marker_scene() -> Scene:
    return build_scene("room", markers_m=MARKERS, marker_radius_m=0.03, max_boxes=0)


def test_pixel_rays_invert_projection() -> None:
    calib = euroc_like_calibration()
    intr = calib.cam0.intrinsics
    xy = pixel_rays(intr)
    proj = intr.project(np.concatenate([xy.reshape(-1, 2), np.ones((xy.size // 2, 1))], 1))
    uu, vv = np.meshgrid(np.arange(intr.width), np.arange(intr.height))
    err = np.abs(proj - np.stack([uu.ravel(), vv.ravel()], 1))
    assert err.max() < 1e-6


def test_markers_project_onto_rendered_texels(marker_scene: Scene) -> None:
    """A world point painted on a wall/floor appears (blob centroid) where the calibration's
    project(cam_from_body @ body_from_world @ point) says, in both cameras."""
    calib = euroc_like_calibration()
    renderer = StereoRenderer(marker_scene, calib.cameras)
    world_from_body = _body_pose(np.array([1.2, 0.2, 1.5]), yaw=0.15, pitch=0.1, roll=0.05)
    outs = renderer.render(world_from_body)
    checked = 0
    for cam, out in zip(calib.cameras, outs):
        cam_from_world = invert_transform(world_from_body @ cam.body_from_cam)
        for m in MARKERS:
            p_cam = transform_points(cam_from_world, np.array([m]))
            if p_cam[0, 2] <= 0.2:
                continue
            u, v = cam.intrinsics.project(p_cam)[0]
            if not (30 <= u < cam.intrinsics.width - 30 and 30 <= v < cam.intrinsics.height - 30):
                continue
            r = 8  # inside the black square around the disc
            c0, r0 = int(round(u)) - r, int(round(v)) - r
            win = out.image[r0 : r0 + 2 * r + 1, c0 : c0 + 2 * r + 1].astype(float)
            yy, xx = np.mgrid[r0 : r0 + 2 * r + 1, c0 : c0 + 2 * r + 1]
            w = np.clip(win - 10.0, 0, None)
            assert w.sum() > 1000, "marker not visible where it should be"
            cu, cv = (w * xx).sum() / w.sum(), (w * yy).sum() / w.sum()
            assert abs(cu - u) < 0.25 and abs(cv - v) < 0.25, (cam.name, m, (u, v), (cu, cv))
            checked += 1
    assert checked >= 4


def _analytic_depth(scene: Scene, world_from_cam: np.ndarray, xy: np.ndarray) -> np.ndarray:
    """Depth z of the nearest face hit by rays (x, y, 1), float64, one face at a time."""
    dirs = np.concatenate([xy, np.ones((len(xy), 1))], 1) @ world_from_cam[:3, :3].T
    origin = world_from_cam[:3, 3]
    best = np.full(len(xy), np.inf)
    for f in scene.faces:
        with np.errstate(divide="ignore", invalid="ignore"):
            t = (f.plane_m - origin[f.axis]) / dirs[:, f.axis]
        p = origin + t[:, None] * dirs
        inside = (
            (t > 0)
            & (p[:, f.u_axis] >= f.u_range_m[0])
            & (p[:, f.u_axis] <= f.u_range_m[1])
            & (p[:, f.v_axis] >= f.v_range_m[0])
            & (p[:, f.v_axis] <= f.v_range_m[1])
        )
        best = np.where(inside & (t < best), t, best)
    return best


@pytest.mark.parametrize("kind", ["room", "hall"])
def test_depth_matches_analytic_ray_plane_distance(kind: str) -> None:
    calib = euroc_like_calibration()
    scene = build_scene(kind, seed=1)
    cam = calib.cameras[0]
    renderer = CameraRenderer(scene, cam)
    rays = pixel_rays(cam.intrinsics)
    rng = np.random.default_rng(0)
    for k in range(3):
        pos = np.array([rng.uniform(-1.5, 1.5), rng.uniform(-0.8, 0.8), rng.uniform(1.0, 2.0)])
        # keep the camera out of boxes
        if scene.clearance_m(pos[None])[0] < 0.3:
            continue
        world_from_cam = _body_pose(pos, 2.1 * k, 0.2, 0.1) @ cam.body_from_cam
        depth = renderer.render(world_from_cam, with_depth=True).depth_m
        assert depth is not None and depth.dtype == np.float32
        assert np.array_equal(renderer.render_depth(world_from_cam), depth)
        uv = np.stack([rng.integers(0, 752, 2000), rng.integers(0, 480, 2000)], 1)
        xy = rays[uv[:, 1], uv[:, 0]]  # exact inverse of project (tested above)
        expected = _analytic_depth(scene, world_from_cam, xy)
        got = depth[uv[:, 1], uv[:, 0]].astype(float)
        err = np.abs(got - expected)
        assert np.isfinite(expected).all()
        assert np.median(err) < 1e-4 * np.median(expected)
        assert np.quantile(err, 0.99) < 1e-3  # a few rays graze box edges


def test_back_projected_depth_lies_on_scene_surface() -> None:
    calib = euroc_like_calibration()
    scene = build_scene("room", seed=2)
    cam = calib.cameras[1]
    world_from_cam = _body_pose(np.array([-1.0, 0.5, 1.4]), -2.5, 0.3, 0.0) @ cam.body_from_cam
    depth = CameraRenderer(scene, cam).render(world_from_cam, with_depth=True).depth_m
    assert depth is not None
    rng = np.random.default_rng(1)
    uv = np.stack([rng.integers(0, 752, 500), rng.integers(0, 480, 500)], 1).astype(float)
    xy = pixel_rays(cam.intrinsics)[uv[:, 1].astype(int), uv[:, 0].astype(int)]
    z = depth[uv[:, 1].astype(int), uv[:, 0].astype(int)]
    p_world = transform_points(
        world_from_cam, np.concatenate([xy, np.ones((500, 1))], 1) * z[:, None]
    )
    dist = np.full(500, np.inf)
    for f in scene.surface_faces():
        dist = np.minimum(dist, np.abs(p_world[:, f.axis] - f.plane_m))
    assert np.quantile(dist, 0.99) < 1e-3

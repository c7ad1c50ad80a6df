"""The monocular front end's two-view start: a pure rotation is refused (no parallax, no
scale), a translation gives the structure up to scale."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from datasets.rigs import euroc_like_calibration
from slam.config import FrontendConfig
from slam.core.geometry import invert_transform, make_transform, transform_points
from slam.core.messages import StereoFrame
from slam.frontend.mono import MonoFrontEnd, _Reference


@pytest.fixture(scope="module")
def scene():
    calib = euroc_like_calibration(distortion=False)
    mono = dataclasses.replace(calib, cameras=calib.cameras[:1])
    intr = mono.cameras[0].intrinsics
    rng = np.random.default_rng(0)
    n = 150
    px = rng.uniform([60, 60], [intr.width - 60, intr.height - 60], (n, 2))
    depth = rng.uniform(2.0, 6.0, n)
    pts_c0 = np.hstack([(px - [intr.cx, intr.cy]) / [intr.fx, intr.fy], np.ones((n, 1))])
    return mono, intr, pts_c0 * depth[:, None]


def _reference(intr, pts_c0, c1_from_c0):
    pts_c1 = transform_points(c1_from_c0, pts_c0)
    px0 = intr.project(pts_c0).astype(np.float32)
    px1 = intr.project(pts_c1).astype(np.float32)
    return _Reference(0, px0, px1, np.eye(4))


def _frame(intr):
    return StereoFrame(
        t_ns=50_000_000, left=np.zeros((intr.height, intr.width), np.uint8), right=None
    )


def test_pure_rotation_is_refused(scene):
    mono, intr, pts = scene
    fe = MonoFrontEnd(mono, FrontendConfig())
    rot = make_transform(
        np.array([[np.cos(0.1), 0, np.sin(0.1)], [0, 1, 0], [-np.sin(0.1), 0, np.cos(0.1)]]),
        np.zeros(3),
    )  # 5.7 deg about y: 60+ px of displacement, no parallax
    ref = _reference(intr, pts, rot)
    assert (
        np.median(np.linalg.norm(ref.px - ref.px0, axis=1))
        > FrontendConfig().mono_init_min_parallax_px
    )
    assert fe._two_view(_frame(intr), ref) is None


def test_translation_gives_the_structure_up_to_scale(scene):
    mono, intr, pts = scene
    fe = MonoFrontEnd(mono, FrontendConfig())
    c1_from_c0 = invert_transform(make_transform(np.eye(3), np.array([0.25, 0.02, 0.05])))
    made = fe._two_view(_frame(intr), _reference(intr, pts, c1_from_c0))
    assert made is not None
    pts_world, rows, world_from_body, continues = made
    assert not continues and len(rows) >= 0.9 * len(pts)
    # the reference body is the world origin: back into its camera, the points are the truth
    # times one scale, chosen so that their median depth is mono_init_depth_m
    cam0_from_world = invert_transform(mono.cameras[0].body_from_cam)
    est = transform_points(cam0_from_world, pts_world)
    k = np.median(est[:, 2]) / np.median(pts[rows, 2])
    assert np.median(est[:, 2]) == pytest.approx(FrontendConfig().mono_init_depth_m, rel=1e-6)
    assert np.abs(est - k * pts[rows]).max() < 0.01 * k * pts[rows, 2].max()
    # and the second camera sits along the true baseline direction
    world_from_cam1 = world_from_body @ mono.cameras[0].body_from_cam
    centre = transform_points(cam0_from_world, world_from_cam1[:3, 3][None])[0]
    truth = np.array([0.25, 0.02, 0.05])
    assert (
        np.degrees(np.arccos(centre @ truth / np.linalg.norm(centre) / np.linalg.norm(truth))) < 1.0
    )


def test_keyframes_come_at_least_every_interval_until_the_scale_is_known(scene):
    """``mono_init_keyframe_interval_s``: with every landmark still tracked and no parallax the
    usual rules make no keyframe before ``keyframe_max_interval_s``; until the back end has
    fixed the scale (``reframed``) one comes after the interval, afterwards the usual rules
    apply again; off (the default), nothing changes."""
    mono, intr, _ = scene
    cfg = FrontendConfig(mono_init_keyframe_interval_s=0.2)
    assert FrontendConfig().mono_init_keyframe_interval_s == 0.0
    assert cfg.mono_init_keyframe_interval_s < cfg.keyframe_max_interval_s
    rng = np.random.default_rng(1)
    px = rng.uniform([0, 0], [intr.width, intr.height], (100, 2)).astype(np.float32)

    def tracking(fe):
        fe.ids = np.arange(100, dtype=np.int64)
        fe.px = px.copy()
        fe.kf_px = {i: px[i].copy() for i in range(100)}
        fe.kf_num_landmarks = 100
        fe.kf_t_ns = 1_000_000_000
        return fe

    off, on = tracking(MonoFrontEnd(mono, FrontendConfig())), tracking(MonoFrontEnd(mono, cfg))
    for since_s, want_on in ((0.1, False), (0.19, False), (0.21, True), (0.4, True)):
        t_ns = 1_000_000_000 + int(since_s * 1e9)
        assert not off._need_keyframe(t_ns, 100)
        assert on._need_keyframe(t_ns, 100) is want_on
    on.reframed = True  # the scale is known: the usual rules
    assert not on._need_keyframe(1_000_000_000 + int(0.4e9), 100)
    assert on._need_keyframe(1_000_000_000 + int(0.5e9), 100)

"""PatchMatch stereo on the synthetic room (small image: numpy PatchMatch is slow)."""

from __future__ import annotations

import numpy as np
import pytest
from synthetic_planes import PlaneScene, look_at

from mapping.patchmatch import PatchMatchConfig, patchmatch_stereo
from mapping.planesweep import SourceView
from slam.core.geometry import invert_transform

K = np.array([[115.0, 0.0, 80.0], [0.0, 115.0, 60.0], [0.0, 0.0, 1.0]])
HW = (120, 160)


@pytest.fixture(scope="module")
def views():
    scene = PlaneScene()
    ref_pose = look_at(np.array([-0.5, -0.3, 1.3]), np.array([1.5, 0.8, 0.3]))
    img, depth = scene.render(ref_pose, K, HW)
    sources = []
    for shift in (np.array([0.15, 0.0, 0.0]), np.array([-0.12, 0.1, 0.0])):
        pose = ref_pose.copy()
        pose[:3, 3] += ref_pose[:3, :3] @ shift
        im, _ = scene.render(pose, K, HW)
        sources.append(SourceView(im, K, invert_transform(pose) @ ref_pose))
    return img, depth, sources


@pytest.mark.parametrize("slanted", [False, True])
def test_patchmatch_recovers_depth(views, slanted):
    img, depth, sources = views
    cfg = PatchMatchConfig(depth_min_m=0.5, depth_max_m=6.0, slanted=slanted, iterations=3)
    res = patchmatch_stereo(img, K, sources, cfg)
    ok = res.valid & (depth > 0)
    assert ok.mean() > 0.7
    assert np.median(np.abs(res.depth_m[ok] - depth[ok]) / depth[ok]) <= 0.02


def test_patchmatch_is_deterministic_for_a_seed(views):
    img, _, sources = views
    cfg = PatchMatchConfig(depth_min_m=0.5, depth_max_m=6.0, iterations=1)
    a = patchmatch_stereo(img, K, sources, cfg)
    b = patchmatch_stereo(img, K, sources, cfg)
    np.testing.assert_array_equal(a.raw_depth_m, b.raw_depth_m)

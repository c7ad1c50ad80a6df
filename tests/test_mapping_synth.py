"""Plane sweep on the project's synthetic stereo sequence (EuRoC-like cameras, radtan)."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from mapping.planesweep import SourceView, SweepConfig, Undistorter, plane_sweep
from slam.core.geometry import invert_transform

synth = pytest.importorskip("datasets.synth")


def test_sweep_on_synthetic_sequence_keyframe():
    seq = synth.make_synthetic_sequence("figure8", duration_s=8.0, seed=0)
    calib = seq.calibration
    und0 = Undistorter(calib.cameras[0].intrinsics)
    und1 = Undistorter(calib.cameras[1].intrinsics)
    s = 0.5  # half resolution keeps the test fast

    def half(img, interp=cv2.INTER_AREA):
        return cv2.resize(img, None, fx=s, fy=s, interpolation=interp)

    def scaled(k):
        k = k.copy()
        k[:2] *= s
        return k

    i_ref, i_prev = 120, 110
    ref = seq.frame(i_ref)
    prev = seq.frame(i_prev)
    pose = seq.world_from_cam(i_ref, 0)
    sources = [
        SourceView(half(und1(ref.right)), scaled(und1.K), calib.cam1_from_cam0()),
        SourceView(
            half(und0(prev.left)),
            scaled(und0.K),
            invert_transform(seq.world_from_cam(i_prev, 0)) @ pose,
        ),
    ]
    truth = half(und0(seq.depth(i_ref), cv2.INTER_NEAREST), cv2.INTER_NEAREST)
    res = plane_sweep(
        half(und0(ref.left)),
        scaled(und0.K),
        sources,
        SweepConfig(depth_min_m=0.4, depth_max_m=8.0, window=5),
    )
    ok = res.valid & (truth > 0)
    rel = np.abs(res.depth_m[ok] - truth[ok]) / truth[ok]
    assert np.median(rel) <= 0.02, np.median(rel)
    assert (res.valid & res.textured).sum() / res.textured.sum() >= 0.70

"""Relocalisation against keyframes stored by the loop closer (synthetic ``loop`` profile)."""

from __future__ import annotations

import numpy as np
import pytest

from datasets.synth.keyframes import Drift, ground_truth_keyframes
from slam.core.geometry import invert_transform, so3_log
from slam.loop.closer import LoopCloser
from slam.loop.relocaliser import Relocaliser


@pytest.fixture(scope="module")
def stored():
    """The first 30 s of the loop profile as keyframes (drifted odometry), in a closer."""
    from datasets.synth import make_synthetic_sequence

    seq = make_synthetic_sequence(profile="loop", seed=1)
    drift = Drift(yaw_deg_per_s=0.05, translation_m_per_s=(0.003, -0.002, 0.001))
    kfs = ground_truth_keyframes(seq, list(range(40, 640, 20)), drift)
    closer = LoopCloser(seq.calibration)
    for s in kfs:
        closer.add_keyframe(s.keyframe, s.world_from_body_odom)
    return seq, kfs, closer


def render_left(seq, index: int) -> tuple[np.ndarray, int, np.ndarray]:
    t_ns = int(seq.frame_times_ns()[index])
    world_from_body = seq.world_from_body_at(t_ns)
    cam = seq.calibration.cameras[0]
    return (
        seq.renderer.cameras[0].render(world_from_body @ cam.body_from_cam).image,
        t_ns,
        world_from_body,
    )


@pytest.mark.parametrize("index", [1570, 1590, 330])
def test_relocalise_revisit_in_the_stored_frame(stored, index: int) -> None:
    """A frame of the second lap (or between stored keyframes) is found; its pose, in the
    matched keyframe's (drifted) odometry frame, is within a few cm of the truth there."""
    seq, kfs, closer = stored
    reloc = Relocaliser(seq.calibration, closer.store, vocabulary=closer.vocab)
    image, t_ns, true_pose = render_left(seq, index)
    res = reloc.relocalise(image, t_ns)
    assert res is not None
    match = next(s for s in kfs if s.keyframe.keyframe_id == res.keyframe_id)
    # the store's frame: the matched keyframe's odometry pose is where truth says it is
    expected = match.world_from_body_odom @ invert_transform(match.world_from_body_true) @ true_pose
    assert np.linalg.norm(res.world_from_body[:3, 3] - expected[:3, 3]) < 0.03
    angle = np.linalg.norm(so3_log(res.world_from_body[:3, :3].T @ expected[:3, :3]))
    assert np.degrees(angle) < 1.0
    assert res.inliers >= 25
    assert res.segment_id == 0


def test_relocalise_unknown_place_returns_none(stored) -> None:
    """The far side of the ellipse was never stored: no pose rather than a wrong one."""
    seq, _, closer = stored
    reloc = Relocaliser(seq.calibration, closer.store, vocabulary=closer.vocab)
    image, t_ns, _ = render_left(seq, 900)
    assert reloc.relocalise(image, t_ns) is None
    assert reloc.calls == 1 and reloc.successes == 0

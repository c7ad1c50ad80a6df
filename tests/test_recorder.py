"""The recorder's odometry chain without the front end's corrections."""

from __future__ import annotations

import numpy as np
from conftest import tracking_result

from slam.core.geometry import so3_exp_batch
from slam.core.messages import FrontendCorrection
from slam.runtime.recorder import Recorder


def _pose(rotvec: np.ndarray, t: np.ndarray) -> np.ndarray:
    pose = np.eye(4)
    pose[:3, :3] = so3_exp_batch(np.asarray(rotvec, float)[None])[0]
    pose[:3, 3] = t
    return pose


def test_continuous_odometry_undoes_the_front_ends_corrections() -> None:
    """Frames published in a world the front end moved twice after its change of frame (map
    reuse, re-anchoring): the chain is the true motion in the first frame's world again,
    every pose moved by the change of frame as the outputs are, which keep the poses as
    published."""
    rng = np.random.default_rng(3)
    truth = [_pose(rng.normal(0, 0.3, 3), rng.normal(0, 1.0, 3)) for _ in range(12)]
    reframe = _pose(np.array([0.0, 0.4, 0.1]), np.array([1.0, -2.0, 0.5]))
    changes = {
        4: _pose(np.array([0.01, -0.02, 0.03]), np.array([0.02, 0.0, -0.01])),
        8: _pose(np.array([0.0, 0.0, 0.05]), np.array([0.0, 0.1, 0.0])),
    }
    rec = Recorder(0)
    assert rec.continuous_odometry(0).shape == (0, 4, 4)
    rec.put(tracking_result(0, truth[0], frame_index=0))
    np.testing.assert_array_equal(rec.continuous_odometry(1), truth[0][None])  # no correction yet
    rec = Recorder(0)
    world = np.eye(4)  # the front end's world from the true one
    for k, pose in enumerate(truth):
        if k == 2:
            rec.put(FrontendCorrection(k * 50_000_000, reframe, True))
            world = reframe @ world
        if k in changes:
            rec.put(FrontendCorrection(k * 50_000_000, changes[k], False))
            world = changes[k] @ world
        rec.put(tracking_result(k * 50_000_000, world @ pose, frame_index=k))
    chain = rec.continuous_odometry(len(truth))
    np.testing.assert_allclose(chain, np.array([reframe @ p for p in truth]), atol=1e-12)
    np.testing.assert_allclose(rec.continuous_odometry(6), chain[:6], atol=0)
    assert rec.correction_frames(len(truth)).tolist() == [4, 8]  # not the change of frame
    assert rec.correction_frames(6).tolist() == [4]
    published = rec.snapshot()[0].matrices()
    assert np.abs(published[10] - chain[10]).max() > 0.05


def test_bridged_chain_removes_the_step_a_correction_left() -> None:
    """A smooth flight at 20 Hz; after two corrections the front end's frames are off by
    what the undone move did not carry (8 and 12 mm, as a re-anchoring's landmarks leave): the
    bridged chain follows the true motion again, to well under a millimetre, and leaves
    frames before the first correction and across a new map segment alone."""
    from slam.loop.closer import bridge_corrections

    t = np.arange(60) * 0.05
    truth = np.array(
        [_pose(np.array([0.0, 0.0, 0.4 * s]), np.array([np.cos(s), np.sin(s), 0.1 * s])) for s in t]
    )
    chain = truth.copy()
    chain[20:, :3, 3] += [0.008, 0.0, 0.0]  # left by the correction at frame 20
    chain[41:, :3, 3] += [0.0, -0.012, 0.0]  # and at frame 41
    segments = np.zeros(60, dtype=int)
    bridged = bridge_corrections(chain, np.array([20, 41]), segments)
    # the steps are gone: every frame-to-frame motion within 0.5 mm of the truth's
    error = np.diff(bridged[:, :3, 3], axis=0) - np.diff(truth[:, :3, 3], axis=0)
    assert np.abs(np.diff(chain[:, :3, 3], axis=0) - np.diff(truth[:, :3, 3], axis=0)).max() > 0.007
    assert np.abs(error).max() < 5e-4
    np.testing.assert_array_equal(bridged[:20], chain[:20])
    np.testing.assert_array_equal(bridged[:, :3, :3], chain[:, :3, :3])  # rotations untouched
    # a correction at the first frame of a new map segment: no motion across it to bridge
    segments[41:] = 1
    np.testing.assert_array_equal(bridge_corrections(chain, np.array([41]), segments), chain)
    np.testing.assert_array_equal(bridge_corrections(chain, np.array([], int), segments), chain)

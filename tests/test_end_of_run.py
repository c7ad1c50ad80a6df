"""The keyframe trajectory written at the end of a run."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np

from slam.core.geometry import make_transform, so3_exp
from slam.runtime.end_of_run import keyframe_trajectory
from slam.runtime.outputs import trajectory_from_poses


def _pose(k: int) -> np.ndarray:
    return make_transform(so3_exp(np.array([0.0, 0.0, 0.1 * k])), [0.2 * k, 0.05 * k, 0.0])


def test_keyframes_after_the_back_ends_last_estimate_follow_it_by_the_front_ends_motion():
    """An interrupted run (the back end's backlog skipped) or one stopped just after a late
    initialisation: the back end estimated keyframes 1 and 2 of 0..5 in its own world. Keyframe
    0 (before its initialisation) stays out; 3..5 follow keyframe 2 by the front end's motion;
    none is lost."""
    times = {k: 1_000_000_000 + k * 100_000_000 for k in range(6)}
    map_from_front = make_transform(so3_exp(np.array([0.3, -0.1, 1.0])), [1.0, 2.0, 3.0])
    front = [(times[k], _pose(k)) for k in range(6)]
    est = {k: map_from_front @ _pose(k) for k in (1, 2)}
    est[1] = est[1] @ make_transform(np.eye(3), [0.01, 0.0, 0.0])  # smoothed: not rigid
    backend = SimpleNamespace(keyframe_poses=est)
    recorder = SimpleNamespace(keyframe_times_copy=lambda: dict(times))
    kfs = keyframe_trajectory(trajectory_from_poses(front), backend, recorder)  # type: ignore[arg-type]
    assert kfs.t_ns.tolist() == [times[k] for k in range(1, 6)]
    got = kfs.matrices()
    np.testing.assert_allclose(got[0], est[1], atol=1e-9)
    for row, k in enumerate(range(2, 6), start=1):
        np.testing.assert_allclose(got[row], map_from_front @ _pose(k), atol=1e-9)

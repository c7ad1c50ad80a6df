"""The loop stages' odometry refresh: late frame changes reach every keyframe, invalid poses
from the source are ignored."""

from __future__ import annotations

import numpy as np

from slam.core.geometry import make_transform, so3_exp
from slam.loop.odometry import (
    FULL_REFRESH_EVERY,
    REFRESH_LAST_KEYFRAMES,
    OdometryRefresher,
    before_first_smoothed,
)


def _new_keyframe_along_x(ref: OdometryRefresher, poses: dict[int, np.ndarray], k: int) -> None:
    """Keyframe ``k`` 0.1 k m along x, handed to the refresher as a new keyframe."""
    poses[k] = make_transform(np.eye(3), [0.1 * k, 0.0, 0.0])
    ref.new_keyframe(k, poses[k])


def test_late_frame_change_reaches_old_keyframes() -> None:
    """A change of frame that arrives after the first keyframes left the recent window is
    still resent within FULL_REFRESH_EVERY keyframes."""
    poses: dict[int, np.ndarray] = {}
    ref = OdometryRefresher(poses.get)
    n_before = REFRESH_LAST_KEYFRAMES + 15
    for k in range(n_before):
        ref.refreshed()  # (reads only keyframes already handed over, never k)
        _new_keyframe_along_x(ref, poses, k)
    new_from_old = make_transform(so3_exp(np.array([0.0, np.pi / 2, 0.0])), [1.0, 2.0, 3.0])
    for k in poses:
        poses[k] = new_from_old @ poses[k]
    resent: dict[int, np.ndarray] = {}
    for k in range(n_before, n_before + FULL_REFRESH_EVERY):
        resent.update(ref.refreshed())
        _new_keyframe_along_x(ref, poses, k)
    assert set(range(n_before)) <= set(resent)
    np.testing.assert_allclose(resent[0], poses[0])
    # nothing changed since: nothing is resent
    for _ in range(FULL_REFRESH_EVERY):
        assert not ref.refreshed()
        k = max(poses) + 1
        poses[k] = np.eye(4)
        ref.new_keyframe(k, poses[k])


def test_invalid_source_poses_are_ignored() -> None:
    bad = np.eye(4)
    bad[:3, :3] *= 3.0  # not a rotation
    nan = np.full((4, 4), np.nan)
    poses = {0: np.eye(4), 1: bad, 2: nan}
    ref = OdometryRefresher(poses.get)
    fallback = make_transform(np.eye(3), [1.0, 0.0, 0.0])
    for k in range(3):
        ref.refreshed()
        sent = ref.new_keyframe(k, fallback)
        expected = poses[0] if k == 0 else fallback
        np.testing.assert_allclose(sent, expected)
    assert ref.invalid_poses >= 2


def test_small_drift_of_old_keyframes_is_not_resent() -> None:
    """Front-end poses of keyframes without a back-end pose follow every drift re-anchoring:
    once outside the recent window, their small moves are ignored (they would accumulate)."""
    poses: dict[int, np.ndarray] = {}
    ref = OdometryRefresher(poses.get)
    n = REFRESH_LAST_KEYFRAMES + 5
    for k in range(n):
        ref.refreshed()  # (reads only keyframes already handed over, never k)
        _new_keyframe_along_x(ref, poses, k)
    original = poses[0].copy()
    resent: set[int] = set()
    for k in range(n, n + 10 * FULL_REFRESH_EVERY):
        poses[0] = make_transform(np.eye(3), [0.0, 0.002, 0.0]) @ poses[0]  # 2 mm per keyframe
        resent |= set(ref.refreshed())
        _new_keyframe_along_x(ref, poses, k)
    assert 0 not in resent
    np.testing.assert_allclose(ref.sent[0], original)
    assert ref.frame_jumps == 0


def test_only_keyframes_before_the_back_ends_first_are_left_out() -> None:
    """Keyframes 0-2 predate the back end's initialisation; 9 is the newest, which the back end
    has not reached yet at the end of the run: it must stay in the global adjustment."""
    smoothed = set(range(3, 9))
    assert before_first_smoothed(list(range(10)), smoothed.__contains__) == {0, 1, 2}
    assert before_first_smoothed(list(range(10)), lambda k: False) == set()
    assert before_first_smoothed([], smoothed.__contains__) == set()


def test_keyframes_before_initialisation_follow_the_first_estimated_one() -> None:
    """Keyframes the back end never estimated (before its initialisation) keep their visual-
    odometry pose relative to the first one it did, and move with its estimate: as the front
    end's belief they stayed where its first estimate put them (15 mm off on room-figure8)."""
    from types import SimpleNamespace

    from slam.core.geometry import invert_transform
    from slam.runtime.loop import _OdometrySource

    src = _OdometrySource()
    vo = {
        k: make_transform(so3_exp(np.array([0.0, 0.0, 0.01 * k])), [0.05 * k, 0, 0])
        for k in range(4)
    }
    for k in range(4):
        src.add_keyframe(SimpleNamespace(keyframe_id=k, world_from_body_vo=vo[k]))

    def estimate(poses: dict[int, np.ndarray]) -> SimpleNamespace:
        return SimpleNamespace(estimate=SimpleNamespace(initialized=True, keyframe_poses=poses))

    assert np.array_equal(src(0), vo[0])  # nothing estimated yet: the belief
    first = make_transform(so3_exp(np.array([0.1, 0.0, 0.0])), [1.0, 2.0, 0.5])
    src.backend_output(estimate({2: first, 3: first @ invert_transform(vo[2]) @ vo[3]}))
    for k in (0, 1):
        np.testing.assert_allclose(src(k), first @ invert_transform(vo[2]) @ vo[k], atol=1e-12)
    smoothed = make_transform(np.eye(3), [0.015, 0.0, 0.0]) @ first  # the window refines it
    src.backend_output(estimate({2: smoothed}))
    np.testing.assert_allclose(
        invert_transform(src(2)) @ src(0), invert_transform(vo[2]) @ vo[0], atol=1e-12
    )
    np.testing.assert_allclose(
        src(0)[:3, 3] - src(2)[:3, 3],
        smoothed[:3, :3] @ (invert_transform(vo[2]) @ vo[0])[:3, 3],
        atol=1e-12,
    )

"""The front end's re-anchoring to back-end estimates keeps every stored pose rigid."""

import numpy as np

from datasets.rigs import euroc_like_calibration
from slam.config import FrontendConfig
from slam.core.geometry import make_transform, nearest_rigid, so3_exp
from slam.core.messages import Estimate
from slam.frontend.tracker import FrontEnd


def _orthonormality_error(pose: np.ndarray) -> float:
    rot = pose[:3, :3]
    return float(np.abs(rot.T @ rot - np.eye(3)).max())


def test_nearest_rigid_projects_onto_se3():
    rng = np.random.default_rng(0)
    pose = make_transform(so3_exp(rng.normal(size=3)), rng.normal(size=3))
    bent = pose.copy()
    bent[:3, :3] *= 1.001
    bent[:3, :3] += rng.normal(scale=1e-4, size=(3, 3))
    fixed = nearest_rigid(bent)
    assert _orthonormality_error(fixed) < 1e-12
    assert np.isclose(np.linalg.det(fixed[:3, :3]), 1.0)
    np.testing.assert_allclose(fixed, pose, atol=2e-3)
    np.testing.assert_array_equal(fixed[:3, 3], bent[:3, 3])


def test_thousands_of_estimates_leave_keyframe_poses_rigid():
    """Each estimate moves every stored keyframe pose by a correction computed from one of them:
    numerical non-orthonormality fed back that way grew until poses overflowed (seen under
    heavy CPU load, when estimates lag). The correction is projected onto SE(3)."""
    fe = FrontEnd(euroc_like_calibration(), FrontendConfig(), None, lambda: estimate)
    rng = np.random.default_rng(1)
    fe.mapped = True
    for kid in range(40):
        pose = make_transform(so3_exp(rng.normal(size=3)), rng.normal(size=3))
        pose[:3, :3] *= 1 + 1e-9  # a slightly non-rigid start, as after many products
        fe.kf_poses[kid] = pose
    for i in range(3000):
        kid = int(rng.integers(0, 40))
        noise = make_transform(
            so3_exp(rng.normal(scale=1e-3, size=3)), rng.normal(scale=1e-3, size=3)
        )
        estimate = Estimate.pose_only(
            i, kid, noise @ fe.kf_poses[kid], initialized=True, map_generation=i
        )
        fe._apply_estimate()
    worst = max(_orthonormality_error(p) for p in fe.kf_poses.values())
    assert np.isfinite(worst) and worst < 1e-6


def test_an_estimate_that_is_not_a_rigid_pose_is_ignored():
    fe = FrontEnd(euroc_like_calibration(), FrontendConfig(), None, lambda: estimate)
    fe.mapped = True
    fe.kf_poses[0] = np.eye(4)
    fe.world_from_body = np.eye(4)
    bad = np.eye(4)
    bad[:3, :3] *= 12.0
    estimate = Estimate.pose_only(5, 0, bad, initialized=True)
    fe._apply_estimate()
    np.testing.assert_array_equal(fe.world_from_body, np.eye(4))
    assert any("not a rigid pose" in text for _, text in fe.stats.state_log)

import numpy as np
from scipy.spatial.transform import Rotation

from slam.core.calibration import Calibration, CameraCalibration, CameraIntrinsics, ImuCalibration
from slam.core.geometry import (
    invert_transform,
    make_transform,
    matrix_to_quat_wxyz,
    quat_wxyz_to_matrix,
)


def test_invert_transform_roundtrip():
    rng = np.random.default_rng(0)
    t = make_transform(Rotation.random(random_state=1).as_matrix(), rng.normal(size=3))
    np.testing.assert_allclose(invert_transform(t) @ t, np.eye(4), atol=1e-12)


def test_quaternion_conventions():
    r = Rotation.from_euler("xyz", [0.1, -0.4, 2.0]).as_matrix()
    q_wxyz = matrix_to_quat_wxyz(r)
    assert q_wxyz[0] >= 0
    np.testing.assert_allclose(quat_wxyz_to_matrix(q_wxyz), r, atol=1e-12)


def test_radtan_projection_inverts_undistortion():
    intr = CameraIntrinsics(
        752,
        480,
        458.654,
        457.296,
        367.215,
        248.375,
        "radtan",
        (-0.28340811, 0.07395907, 0.00019359, 1.76187114e-05),
    )
    pts = np.array([[0.1, -0.2, 1.0], [-0.3, 0.25, 2.0], [0.0, 0.0, 3.0]])
    px = intr.project(pts)
    norm = intr.undistort_points(px)
    np.testing.assert_allclose(norm, pts[:, :2] / pts[:, 2:], atol=1e-9)


def test_radtan_undistortion_is_exact_at_the_image_corners():
    intr = CameraIntrinsics(
        752,
        480,
        458.654,
        457.296,
        367.215,
        248.375,
        "radtan",
        (-0.28340811, 0.07395907, 0.00019359, 1.76187114e-05),
    )
    corners = np.array([[0.0, 0.0], [751.0, 0.0], [0.0, 479.0], [751.0, 479.0], [367.0, 248.0]])
    norm = intr.undistort_points(corners)
    back = intr.project(np.hstack([norm, np.ones((len(norm), 1))]))
    np.testing.assert_allclose(back, corners, atol=1e-6)


def test_calibration_dict_roundtrip():
    cam = CameraCalibration("cam0", CameraIntrinsics(640, 480, 500, 500, 320, 240))
    cal = Calibration((cam,), ImuCalibration(), 1234)
    back = Calibration.from_dict(cal.to_dict())
    assert back.to_dict() == cal.to_dict()


def test_rotation_angle_matches_the_rotation_vector_norm():
    from slam.core.geometry import rotation_angle_rad, so3_exp, so3_log

    rng = np.random.default_rng(4)
    for angle in (0.0, 1e-9, 1e-4, 0.3, 1.0, 2.5, np.pi - 1e-6):
        axis = rng.normal(size=3)
        rot = so3_exp(angle * axis / np.linalg.norm(axis))
        assert abs(rotation_angle_rad(rot) - angle) < 1e-9
        assert abs(rotation_angle_rad(rot) - np.linalg.norm(so3_log(rot))) < 1e-9


def test_so3_right_jacobian_maps_a_rotation_vector_step_to_the_right_increment():
    from slam.core.geometry import so3_exp, so3_log, so3_right_jacobian

    rng = np.random.default_rng(5)
    for angle in (0.0, 1e-7, 0.3, 2.0):
        axis = rng.normal(size=3)
        w = angle * axis / np.linalg.norm(axis)
        d = 1e-6 * rng.normal(size=3)
        increment = so3_log(so3_exp(w).T @ so3_exp(w + d))  # exp(w + d) = exp(w) exp(inc)
        assert np.allclose(increment, so3_right_jacobian(w) @ d, atol=1e-12)

"""Motion blur predicted from the gyro and the exposure (``slam.frontend.motion_blur``) against
the true streaks of a known motion; and the front end's use of it: a blurred frame's PnP pose
fused with the IMU's prediction."""

from __future__ import annotations

import numpy as np
import pytest

from datasets.rigs import euroc_like_calibration
from datasets.synth.imu_sim import exact_imu
from datasets.synth.trajectories import ProfileMotion, SinusoidChannel, TimeWarp
from slam.core.calibration import CameraIntrinsics
from slam.core.geometry import invert_transform, transform_points
from slam.core.messages import ImuSample
from slam.frontend.motion_blur import (
    BlurBound,
    angular_rate_rad_s,
    blur_length_px,
    blur_vectors_px,
)
from slam.imu_buffer import ImuBuffer

# a camera swinging about all three axes (up to ~3 rad/s, as room-aggressive), moving too
_MOTION = ProfileMotion(
    name="swing",
    x=SinusoidChannel(c0=1.0, terms=((0.3, 2.0, 0.1),)),
    y=SinusoidChannel(c0=0.0, terms=((0.2, 1.5, 0.7),)),
    z=SinusoidChannel(c0=1.5),
    yaw=SinusoidChannel(terms=((0.8, 3.0, 0.3),)),
    pitch=SinusoidChannel(terms=((0.3, 4.0, 1.1),)),
    roll=SinusoidChannel(terms=((0.25, 5.0, 2.0),)),
    warp=TimeWarp(0.0, 0.0),
)


def _imu_buffer(t_end_s: float) -> ImuBuffer:
    """The motion's exact gyro at 200 Hz up to ``t_end_s``."""
    t_ns = np.arange(0, int(t_end_s * 1e9) + 1, 5_000_000, dtype=np.int64)
    gyro, accel = exact_imu(_MOTION, t_ns * 1e-9, 9.81)
    buf = ImuBuffer(keep_ns=None)
    for t, g, a in zip(t_ns.tolist(), gyro, accel, strict=True):
        buf.add(ImuSample(t, g, a))
    return buf


def _cam_from_world(t_s: float, body_from_cam: np.ndarray) -> np.ndarray:
    world_from_body = _MOTION.sample(np.array([t_s])).world_from_body()[0]
    return invert_transform(world_from_body @ body_from_cam)


@pytest.mark.parametrize("t_mid_s", [0.9, 1.3, 2.05])
def test_predicted_streaks_match_the_true_motion(t_mid_s: float) -> None:
    """Points seen at a grid of pixels at mid-exposure, at 3 m: where they project at the
    exposure's start and end under the true (rotating and moving) camera poses, against the
    streaks predicted from the half-exposure of gyro before the mid-exposure time."""
    cam = euroc_like_calibration().cam0
    exposure_s = 0.008
    t_mid_ns = int(t_mid_s * 1e9)
    imu = _imu_buffer(t_mid_s)  # samples up to the mid-exposure time only, as the front end has
    rate = angular_rate_rad_s(imu, t_mid_ns, int(exposure_s * 1e9))
    assert rate is not None
    u, v = np.meshgrid(np.linspace(60, 690, 6), np.linspace(50, 430, 5))
    px = np.c_[u.ravel(), v.ravel()]
    mid = _cam_from_world(t_mid_s, cam.body_from_cam)
    rays = np.hstack([cam.intrinsics.undistort_points(px), np.ones((len(px), 1))])
    points_world = transform_points(invert_transform(mid), 3.0 * rays)
    start = cam.intrinsics.project(
        transform_points(_cam_from_world(t_mid_s - exposure_s / 2, cam.body_from_cam), points_world)
    )
    end = cam.intrinsics.project(
        transform_points(_cam_from_world(t_mid_s + exposure_s / 2, cam.body_from_cam), points_world)
    )
    true = end - start
    cam_from_body = invert_transform(cam.body_from_cam)[:3, :3]
    pred = blur_vectors_px(rate, exposure_s, cam_from_body, cam.intrinsics, px)
    lengths = np.linalg.norm(true, axis=1)
    assert lengths.min() > 3.0  # a real blur in every case
    err = np.linalg.norm(pred - true, axis=1)
    # rotation only, its rate from the half-exposure before: within 10 % of the streak + 0.5 px
    assert np.all(err < 0.1 * lengths + 0.5), (err.max(), lengths.max())
    assert blur_length_px(rate, exposure_s, cam_from_body, cam.intrinsics, px) == pytest.approx(
        float(np.median(lengths)), rel=0.1
    )


def test_blur_is_focal_length_times_rate_times_exposure_and_zero_without_exposure() -> None:
    cam = euroc_like_calibration().cam0
    k = cam.intrinsics
    cam_from_body = invert_transform(cam.body_from_cam)[:3, :3]
    omega_cam = np.array([0.0, 2.0, 0.0])  # about the camera's y axis: a horizontal streak
    rate_body = cam_from_body.T @ omega_cam
    centre = np.array([[k.cx, k.cy]])
    vec = blur_vectors_px(rate_body, 0.01, cam_from_body, k, centre)[0]
    assert abs(vec[0]) == pytest.approx(k.fx * 2.0 * 0.01, rel=1e-3)
    assert abs(vec[1]) < 1e-6
    assert blur_length_px(rate_body, 0.0, cam_from_body, k, centre) == 0.0
    # about the optical axis the centre stays sharp
    roll = cam_from_body.T @ np.array([0.0, 0.0, 3.0])
    assert np.linalg.norm(blur_vectors_px(roll, 0.01, cam_from_body, k, centre)) < 1e-6


@pytest.mark.parametrize(
    "intrinsics",
    [
        euroc_like_calibration().cam0.intrinsics,
        CameraIntrinsics(640, 480, 400.0, 410.0, 330.0, 235.0),
        CameraIntrinsics(
            640, 480, 460.0, 460.0, 320.0, 240.0, "equidistant", (-0.01, 0.02, -0.01, 0.002)
        ),
    ],
    ids=["radtan", "pinhole", "equidistant"],
)
def test_the_blur_bound_is_above_every_streak_and_within_2x_of_their_median(
    intrinsics: CameraIntrinsics,
) -> None:
    """``BlurBound``: for random rates (up to 10 rad/s), exposures and pixels all over the image,
    each pixel's streak is at most its bound and the median streak (``blur_length_px``) at most
    the bound of the median; the bound is not so loose as to be useless (median ratio > 0.5)."""
    cam_from_body = invert_transform(euroc_like_calibration().cam0.body_from_cam)[:3, :3]
    bound = BlurBound(intrinsics)
    rng = np.random.default_rng(3)
    ratios = []
    for _ in range(300):
        px = rng.uniform([0, 0], [intrinsics.width - 1, intrinsics.height - 1], (40, 2))
        rate = rng.normal(size=3) * rng.uniform(0.05, 10.0) / np.sqrt(3)
        exposure_s = rng.uniform(0.001, 0.02)
        turn = float(np.linalg.norm(rate)) * exposure_s
        norm = intrinsics.undistort_points(px)
        streaks = np.linalg.norm(
            blur_vectors_px(rate, exposure_s, cam_from_body, intrinsics, px), axis=1
        )
        for k in range(len(px)):
            assert streaks[k] <= bound.length_px(norm[k : k + 1], turn)
        length = blur_length_px(rate, exposure_s, cam_from_body, intrinsics, px, norm)
        assert length == blur_length_px(rate, exposure_s, cam_from_body, intrinsics, px)
        assert length <= bound.length_px(norm, turn)
        assert bound.lowest_px(turn) <= bound.length_px(norm, turn)
        ratios.append(length / bound.length_px(norm, turn))
    assert np.median(ratios) > 0.5
    assert bound.length_px(norm, 0.3) == np.inf  # beyond the largest bounded turn


def test_a_wide_fisheye_gets_no_blur_bound() -> None:
    wide = CameraIntrinsics(640, 480, 200.0, 200.0, 320.0, 240.0, "equidistant", (0.0,) * 4)
    assert BlurBound(wide).length_px(np.zeros((1, 2)), 0.01) == np.inf


def test_a_blurred_frame_pose_leans_on_the_imu_prediction() -> None:
    """``FrontEnd._blurred_pose``: a PnP pose 6 mm (or 0.3 deg) off and the IMU's prediction
    (here the truth) fused by information: the more blur, the closer to the prediction."""
    from slam.config import FrontendConfig
    from slam.core.geometry import make_transform, rotation_angle_rad, so3_exp
    from slam.frontend.tracker import FrontEnd

    calib = euroc_like_calibration(distortion=False)
    cfg = FrontendConfig(blur_pose_prior_min_px=1.0)
    fe = FrontEnd(calib, cfg)
    truth = make_transform(so3_exp(np.array([0.1, -0.3, 0.2])), np.array([1.0, 0.5, 1.2]))
    fe._imu_prior = lambda t_ns: truth.copy()  # type: ignore[method-assign]
    rng = np.random.default_rng(0)
    cam = truth @ calib.cam0.body_from_cam
    pts_cam = np.c_[rng.uniform(-2, 2, (80, 2)), rng.uniform(2, 5, 80)]
    obj = transform_points(cam, pts_cam)
    img = calib.cam0.intrinsics.project(pts_cam)

    def off(pose: np.ndarray) -> tuple[float, float]:
        d = invert_transform(truth) @ pose
        return float(np.linalg.norm(d[:3, 3])), rotation_angle_rad(d[:3, :3])

    shifted = truth @ make_transform(np.eye(3), np.array([0.006, -0.002, 0.001]))
    turned = truth @ make_transform(so3_exp(np.radians([0.3, 0.1, 0.0])), np.zeros(3))
    shift_m, turn_rad = off(shifted)[0], off(turned)[1]
    moved, turned_by = [], []
    for blur in (1.5, 4.0, 10.0):
        fe.blur_px = blur
        moved.append(off(fe._blurred_pose(shifted, obj, img, 0))[0])
        turned_by.append(off(fe._blurred_pose(turned, obj, img, 0))[1])
    assert shift_m > moved[0] > moved[1] > moved[2]
    assert turn_rad > turned_by[0] > turned_by[1] > turned_by[2]
    assert moved[2] < 0.5 * shift_m  # a 10 px blur: nearer the prediction than the PnP


def _fusion_case(world_from_anchor: np.ndarray):
    """A front end whose IMU prediction is ``truth``, and a PnP pose 5 mm / 0.2 deg away from it
    that fits its 60 points' pixels exactly (the PnP's optimum); everything moved by
    ``world_from_anchor`` (where the world's origin is)."""
    from slam.config import FrontendConfig
    from slam.core.geometry import make_transform, so3_exp
    from slam.frontend.tracker import FrontEnd

    calib = euroc_like_calibration(distortion=False)
    fe = FrontEnd(calib, FrontendConfig(blur_pose_prior_min_px=1.0))
    truth = world_from_anchor @ make_transform(
        so3_exp(np.array([0.1, -0.3, 2.2])), np.array([3.0, -2.5, 1.2])
    )
    fe._imu_prior = lambda t_ns: truth.copy()  # type: ignore[method-assign]
    pnp = truth @ make_transform(
        so3_exp(np.radians([0.2, -0.1, 0.05])), np.array([0.004, -0.002, 0.003])
    )
    rng = np.random.default_rng(1)
    pts_cam = np.c_[rng.uniform(-2, 2, (60, 2)), rng.uniform(1.5, 6, 60)]
    obj = transform_points(pnp @ calib.cam0.body_from_cam, pts_cam)
    img = calib.cam0.intrinsics.project(pts_cam)
    return fe, calib, truth, pnp, obj, img


def test_the_fused_pose_minimises_reprojection_plus_prediction() -> None:
    """The fusion against a reference: the pose that minimises the PnP's reprojection error
    (pixel sigma grown by the blur) plus the prediction's prior, found by ``least_squares``
    on the exact projection: the same pose to 2 um / 2 urad, between the two (not at either)."""
    from scipy.optimize import least_squares

    from slam.core.geometry import make_transform, so3_exp, so3_log

    fe, calib, truth, pnp, obj, img = _fusion_case(np.eye(4))
    fe.blur_px = 6.0
    cfg = fe.cfg
    sigma_px = np.hypot(cfg.blur_pose_pixel_sigma_px, cfg.blur_pose_sigma_fraction * fe.blur_px)
    anchor_from_truth = invert_transform(pnp) @ truth
    xi_truth = np.r_[so3_log(anchor_from_truth[:3, :3]), anchor_from_truth[:3, 3]]
    weights = np.r_[[1 / cfg.blur_pose_prior_sigma_rad] * 3, [1 / cfg.blur_pose_prior_sigma_m] * 3]

    def pose(xi: np.ndarray) -> np.ndarray:
        return pnp @ make_transform(so3_exp(xi[:3]), xi[3:])

    def residuals(xi: np.ndarray) -> np.ndarray:
        cam_from_world = invert_transform(pose(xi) @ calib.cam0.body_from_cam)
        px = calib.cam0.intrinsics.project(transform_points(cam_from_world, obj))
        return np.r_[((px - img) / sigma_px).ravel(), weights * (xi - xi_truth)]

    reference = pose(least_squares(residuals, np.zeros(6), xtol=1e-14, ftol=1e-14).x)
    fused = fe._blurred_pose(pnp, obj, img, 0)
    d = invert_transform(reference) @ fused
    assert np.linalg.norm(d[:3, 3]) < 2e-6
    assert np.linalg.norm(so3_log(d[:3, :3])) < 2e-6
    for other in (pnp, truth):
        assert np.linalg.norm((invert_transform(other) @ fused)[:3, 3]) > 5e-4


def test_the_fused_pose_does_not_depend_on_the_world_origin() -> None:
    """The same case in a world moved 20 m and turned: the fused pose moves with it."""
    from slam.core.geometry import make_transform, so3_exp

    moved = make_transform(so3_exp(np.array([0.3, 1.0, -0.4])), np.array([20.0, -7.0, 3.0]))
    fe, _, _, pnp, obj, img = _fusion_case(np.eye(4))
    fe_m, _, _, pnp_m, obj_m, img_m = _fusion_case(moved)
    fe.blur_px = fe_m.blur_px = 6.0
    fused = fe._blurred_pose(pnp, obj, img, 0)
    fused_m = fe_m._blurred_pose(pnp_m, obj_m, img_m, 0)
    np.testing.assert_allclose(moved @ fused, fused_m, atol=1e-9)

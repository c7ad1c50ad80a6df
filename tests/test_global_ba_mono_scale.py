"""The midpoint rule in the IMU factors (``slam.backend.imu.integrate_pieces``'
``midpoint_rotation``, ``loop.global_ba_imu_midpoint``): on exact readings of an analytic
motion the preintegrated velocity change is closer to the truth with it, and a monocular
global adjustment started 1 % off in scale ends closer to the true scale (exact readings,
noiseless pixels: what is left is the integration's own error)."""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Sequence
from typing import Any

import gtsam
import numpy as np
import pytest

from datasets.rigs import euroc_like_calibration
from datasets.synth.imu_sim import simulate_imu
from datasets.synth.trajectories import make_profile
from slam.backend.imu import integrate_pieces, integration_pieces, preintegration_params
from slam.config import preset_config
from slam.core.calibration import Calibration
from slam.core.geometry import invert_transform
from slam.core.messages import KeyframeInertial
from slam.evaluation.align import umeyama
from slam.loop.global_ba import (
    GlobalBaParams,
    KeyframeObservations,
    bias_wander,
    global_bundle_adjustment,
)
from slam.posegraph import PoseEdge

KF_DT_NS = 250_000_000
NUM_KF = 64  # 16 s of figure8
MAP_SCALE = 1.01


def _exact_imu(profile: str, seconds: float):
    calib = euroc_like_calibration()
    assert calib.imu is not None
    motion = make_profile(profile, moving_start=True)
    imu_t = np.arange(0, int(seconds * 1e9) + 1, 5_000_000, dtype=np.int64)
    sim = simulate_imu(motion, imu_t, 0.0, calib.imu, noise=False)
    return calib, motion, sim.arrays


@pytest.mark.parametrize("profile", ["figure8", "aggressive"])
def test_midpoint_rotation_preintegrates_closer_to_the_truth(profile: str) -> None:
    """Over 0.25 s intervals of exact readings: the velocity change the preintegration
    predicts (zero bias) against the motion's own, with and without the midpoint rule."""
    calib, motion, imu = _exact_imu(profile, 6.0)
    assert calib.imu is not None
    gravity = np.array([0.0, 0.0, -calib.imu.gravity_m_s2])
    err: dict[bool, list[float]] = {False: [], True: []}
    for t0 in np.arange(0, 5_500_000_000, KF_DT_NS):
        t1 = int(t0 + KF_DT_NS)
        s = motion.sample(np.array([t0, t1]) * 1e-9)
        rot0 = s.world_from_body()[0][:3, :3]
        pieces = integration_pieces(imu.t_ns, imu.gyro_rad_s, imu.accel_m_s2, int(t0), t1, 0.1)
        assert pieces is not None
        true_dv = s.velocities_m_s[1] - s.velocities_m_s[0] - gravity * KF_DT_NS * 1e-9
        for midpoint in (False, True):
            pim = gtsam.PreintegratedCombinedMeasurements(
                preintegration_params(calib.imu), gtsam.imuBias.ConstantBias()
            )
            integrate_pieces(pim, pieces, midpoint)
            err[midpoint].append(float(np.linalg.norm(rot0 @ pim.deltaVij() - true_dv)))
    start_rule = float(np.sqrt(np.mean(np.square(err[False]))))
    midpoint_rule = float(np.sqrt(np.mean(np.square(err[True]))))
    # measured (start's rule / midpoint rule, RMS): figure8 3.2e-4 / 1.2e-7 m/s, aggressive
    # 3.7e-3 / 5.4e-5 m/s
    assert midpoint_rule < 0.2 * start_rule, (midpoint_rule, start_rule)


def _mono_problem(
    map_scale: float = MAP_SCALE,
    num_kf: int = NUM_KF,
    seed: int = 5,
    num_points: int = 6000,
    accel_offset_m_s2: Callable[[np.ndarray], np.ndarray] | None = None,
):
    """A monocular adjustment's inputs: ``num_kf`` keyframes of figure8 (one camera) every
    0.25 s, exact readings (plus ``accel_offset_m_s2(t_s)`` (N, 3) on the accelerometer's, a
    bias the factors do not know of) and noiseless pixels, the keyframes and landmarks started
    ``map_scale`` too large (positions 3 mm, velocities 0.02 m/s noisy). Returns (calibration,
    observations, starting poses, inertial states, keyframe times, true world_from_body
    (K, 4, 4))."""
    rng = np.random.default_rng(seed)
    stereo = euroc_like_calibration()
    calib = Calibration(stereo.cameras[:1], stereo.imu)
    assert calib.imu is not None
    cam = calib.cameras[0]
    _, motion, imu = _exact_imu("figure8", num_kf * KF_DT_NS * 1e-9)
    accel = imu.accel_m_s2
    if accel_offset_m_s2 is not None:
        accel = accel + accel_offset_m_s2(imu.t_ns * 1e-9)
    kf_t = np.arange(num_kf, dtype=np.int64) * KF_DT_NS
    truth = motion.sample(kf_t * 1e-9)
    true = truth.world_from_body()
    d = rng.standard_normal((num_points, 3))
    pts = truth.positions_m.mean(axis=0) + 5.0 * d / np.linalg.norm(d, axis=1, keepdims=True)
    origin = true[0][:3, 3]
    obs, poses, inertial = {}, {}, {}
    for k, pose in enumerate(true):
        cam_from_world = invert_transform(pose @ cam.body_from_cam)
        x = pts @ cam_from_world[:3, :3].T + cam_from_world[:3, 3]
        uv = (x / np.maximum(x[:, 2:3], 1e-9)) @ cam.intrinsics.K.T
        j = np.flatnonzero(
            (x[:, 2] > 0.5)
            & (uv[:, 0] >= 0)
            & (uv[:, 1] >= 0)
            & (uv[:, 0] < cam.intrinsics.width)
            & (uv[:, 1] < cam.intrinsics.height)
        )
        start = pose.copy()
        start[:3, 3] = origin + map_scale * (pose[:3, 3] - origin) + rng.normal(0, 0.003, 3)
        poses[k] = start
        start_cam_from_world = invert_transform(start @ cam.body_from_cam)
        p_cam = (origin + map_scale * (pts[j] - origin)) @ start_cam_from_world[:3, :3].T
        obs[k] = KeyframeObservations(
            (j * 1000 + k // 4).astype(np.int64),  # a track spans 4 keyframes
            uv[j, :2],
            np.full((len(j), 2), np.nan),
            p_cam + start_cam_from_world[:3, 3],
        )
        pieces = (np.zeros(0), np.zeros((0, 3)), np.zeros((0, 3)))
        if k:
            found = integration_pieces(
                imu.t_ns, imu.gyro_rad_s, accel, int(kf_t[k - 1]), int(kf_t[k]), 0.1
            )
            assert found is not None
            pieces = found
        velocity = map_scale * truth.velocities_m_s[k] + rng.normal(0, 0.02, 3)
        inertial[k] = KeyframeInertial(
            k, int(kf_t[k]), velocity, np.zeros(3), np.zeros(3), k - 1, *pieces
        )
    t_ns = {k: int(kf_t[k]) for k in range(num_kf)}
    return calib, obs, poses, inertial, t_ns, true


def _scale_error(world_from_body: dict[int, np.ndarray], true: np.ndarray) -> float:
    """|truth's Sim(3) scale onto the adjusted keyframe positions - 1|."""
    est = np.array([world_from_body[k][:3, 3] for k in range(len(true))])
    return abs(umeyama(est, true[:, :3, 3], with_scale=True)[2] - 1.0)


def _adjusted(problem, edges: Sequence[PoseEdge] = (), **params: Any) -> tuple[float, int]:
    """The global adjustment of ``problem`` (``_mono_problem``'s tuple) with ``edges`` and
    ``GlobalBaParams(min_observations=5, imu_refit=False, **params)``: (the adjusted
    keyframes' ``_scale_error``, its IMU factors)."""
    calib, obs, poses, inertial, t_ns, true = problem
    p = GlobalBaParams(min_observations=5, imu_refit=False, **params)
    res = global_bundle_adjustment(
        calib, obs, poses, list(edges), [], 0, t_ns, p, inertial=inertial, imu=calib.imu
    )
    assert res is not None
    return _scale_error(res.world_from_body, true), res.imu_factors


def test_midpoint_rotation_holds_a_monocular_scale() -> None:
    """A monocular map (one camera) 1 % too large, 16 s of figure8, keyframes every 0.25 s,
    exact readings and pixels, IMU factors allowing 0.1 % scale error: the adjustment's IMU
    factors pull the scale back; with the midpoint rule what is left of the 1 % is well under
    what the start's rule leaves."""
    problem = _mono_problem()

    def scale_error(midpoint: bool) -> float:
        error, factors = _adjusted(
            problem,
            imu_scale_error=0.001,  # factors as tight as exact readings allow: the rule shows
            imu_midpoint_rotation=midpoint,
        )
        assert factors == NUM_KF - 1
        return error

    start_rule, midpoint_rule = scale_error(False), scale_error(True)
    # measured: 0.017 % with the midpoint rule, 0.041 % with the start's
    assert midpoint_rule < 0.6 * start_rule, (midpoint_rule, start_rule)


def test_odometry_edges_without_imu_factors_hold_no_scale() -> None:
    """Keyframes 20-29 of the monocular problem have no inertial state (as when a scale check
    restarts the smoother), so their 10 intervals have no IMU factor; their odometry edges are
    the relative poses at a smoother's wrong scale (translations 20 % too long), 2 mm / 0.5 mrad
    tight (as a run's). Kept whole, the edges drag the map's scale toward theirs; with
    ``imu_odometry_rotation_only`` they hold the rotations alone and the IMU factors elsewhere
    keep the scale. The edges' rotations are exact: rotation-only edges agree with the
    truth."""
    calib, obs, poses, inertial, t_ns, true = _mono_problem(1.0)
    gap = range(20, 30)
    inertial = {k: st for k, st in inertial.items() if k not in gap}
    problem = (calib, obs, poses, inertial, t_ns, true)
    sigmas = np.array([0.002] * 3 + [0.0005] * 3)  # g2o order: translation first
    edges = []
    for a in range(19, 30):
        rel = invert_transform(true[a]) @ true[a + 1]
        rel[:3, 3] *= 1.2
        edges.append(PoseEdge(a, a + 1, rel, np.diag(1.0 / sigmas**2)))

    def adjusted(rotation_only: bool) -> tuple[float, int]:
        return _adjusted(
            problem, edges, imu_midpoint_rotation=True, imu_odometry_rotation_only=rotation_only
        )

    whole, factors = adjusted(False)
    rotation_only, factors_r = adjusted(True)
    assert factors == factors_r == NUM_KF - 1 - 11
    # measured: 5.8 % whole, 0.006 % rotation-only (0.005 % with no edges at all)
    assert rotation_only < 0.1 * whole, (rotation_only, whole)
    assert rotation_only < 0.001, rotation_only


def _bias_wander(t_s: np.ndarray) -> np.ndarray:
    """An accelerometer bias wandering up to 0.08 m/s^2 within 10 s on two body axes (EuRoC's
    accelerometer random walk, 3e-3 m/s^3/sqrt(Hz), allows 0.01)."""
    return np.stack(
        [
            0.04 * np.sin(2 * np.pi * t_s / 14.0),
            0.04 * np.cos(2 * np.pi * t_s / 9.0 + 1.0),
            0 * t_s,
        ],
        axis=1,
    )


@pytest.mark.parametrize("wandering", [True, False])
def test_bias_walk_factor_against_a_wandering_and_a_still_bias(wandering: bool) -> None:
    """The bias random walk of the IMU factors (``GlobalBaParams.imu_accel_walk_factor``): 24 s
    of the monocular problem. Where the accelerometer's bias wanders ten times further than the
    calibrated walk allows (as EuRoC V1_01's: 0.03-0.18 m/s^2 within 10 s), a bias held to the
    calibrated walk leaves the wander in the factors and the scale takes it up; a walk as loose
    as the data's ends closer to the true scale. Where the bias holds still, the looser walk
    lets the bias take up part of the scale error instead (why it is off by default)."""
    num_kf = 96
    problem = _mono_problem(
        num_kf=num_kf,
        seed=7,
        num_points=3000,
        accel_offset_m_s2=_bias_wander if wandering else None,
    )

    def scale_error(factor: float) -> float:
        error, factors = _adjusted(
            problem, imu_midpoint_rotation=True, imu_accel_walk_factor=factor
        )
        assert factors == num_kf - 1
        return error

    calibrated, loose = scale_error(1.0), scale_error(10.0)
    # measured (walk factor 1 / 10): wandering bias 1.74 % / 0.10 %, still bias 0.19 % / 0.53 %
    # (0.59 % / 0.36 % before x10 loosened the bias prior too)
    if wandering:
        assert loose < 0.5 * calibrated, (loose, calibrated)
    else:
        assert calibrated < loose, (calibrated, loose)


def _walk_states(
    calib: Calibration, walk_factor: float, seconds: float, seed: int
) -> dict[int, KeyframeInertial]:
    """Keyframes every 0.25 s whose bias estimates follow random walks of the calibrated
    densities times ``walk_factor`` (no readings: ``bias_wander`` looks at the biases alone)."""
    assert calib.imu is not None
    rng = np.random.default_rng(seed)
    dt = KF_DT_NS * 1e-9
    n = int(seconds / dt)
    walk = {
        name: np.cumsum(rng.normal(0.0, walk_factor * q * np.sqrt(dt), (n, 3)), axis=0)
        for name, q in (("a", calib.imu.accel_random_walk), ("g", calib.imu.gyro_random_walk))
    }
    empty = (np.zeros(0), np.zeros((0, 3)), np.zeros((0, 3)))
    return {
        k: KeyframeInertial(k, k * KF_DT_NS, np.zeros(3), walk["g"][k], walk["a"][k], k - 1, *empty)
        for k in range(n)
    }


@pytest.mark.parametrize("walk_factor", [1.0, 3.0])
def test_bias_wander_measures_the_walk_against_its_calibration(walk_factor: float) -> None:
    """``bias_wander`` of biases that follow random walks of the calibrated densities (times
    ``walk_factor``), 600 s: the median of a chi-square with 3 degrees of freedom over 3
    (0.79) times the factor squared, for both sensors."""
    calib = euroc_like_calibration()
    assert calib.imu is not None
    wander = bias_wander(_walk_states(calib, walk_factor, 600.0, seed=3), calib.imu)
    assert wander is not None
    expected = 0.79 * walk_factor**2
    # measured: 0.80 / 0.77 at 1, 7.4 / 7.0 at 3 (accelerometer / gyro)
    for value in wander:
        assert 0.75 * expected < value < 1.25 * expected, (wander, expected)
    assert bias_wander(_walk_states(calib, 1.0, 5.0, seed=3), calib.imu) is None


@pytest.mark.parametrize("wandering", [True, False])
def test_walk_gate_loosens_the_walk_only_where_the_bias_wandered(wandering: bool) -> None:
    """``GlobalBaParams.imu_walk_gate`` at ``euroc-mono-imu``'s factors and gate: the monocular
    problem with a back end's accelerometer bias estimates that wandered (as ``_bias_wander``:
    0.08 m/s^2 within 10 s) or held still, the gyro's still. The accelerometer's walk factor
    applies only in the first case, the gyro's in neither; a gated adjustment that applies a
    factor is the adjustment with that factor exactly, one that applies none the calibrated
    one."""
    calib, obs, poses, inertial, t_ns, true = _mono_problem(num_kf=48, num_points=2000)
    wander = _bias_wander(np.array([t_ns[k] for k in sorted(t_ns)]) * 1e-9)
    if wandering:
        inertial = {
            k: s.with_state(s.velocity_world_m_s, s.bias_gyro_rad_s, wander[k])
            for k, s in inertial.items()
        }

    def adjust(**params: Any):
        p = GlobalBaParams(min_observations=5, imu_refit=False, imu_midpoint_rotation=True)
        res = global_bundle_adjustment(
            calib,
            obs,
            poses,
            [],
            [],
            0,
            t_ns,
            dataclasses.replace(p, **params),
            inertial=inertial,
            imu=calib.imu,
        )
        assert res is not None
        return res

    loop = preset_config("euroc-mono-imu").loop  # the monocular preset's factors and gate
    assert loop.global_ba_imu_accel_walk_factor == 1000.0 and loop.global_ba_imu_walk_gate > 0
    assert loop.global_ba_imu_accel_bias_smoothing == 0.015
    smoothing = loop.global_ba_imu_accel_bias_smoothing
    gated = adjust(
        imu_accel_walk_factor=loop.global_ba_imu_accel_walk_factor,
        imu_gyro_walk_factor=loop.global_ba_imu_gyro_walk_factor,
        imu_walk_gate=loop.global_ba_imu_walk_gate,
        imu_accel_bias_smoothing=smoothing,
    )
    assert gated.imu_bias_wander is not None
    accel_wander, gyro_wander = gated.imu_bias_wander
    assert gyro_wander == 0.0
    assert (accel_wander >= loop.global_ba_imu_walk_gate) == wandering, accel_wander
    assert gated.imu_walk_factors == ((1000.0, 1.0) if wandering else (1.0, 1.0))
    # the smoothing too applies only with the factor: at factor 1 the calibrated adjustment
    same = adjust(
        imu_accel_walk_factor=1000.0 if wandering else 1.0,
        imu_accel_bias_smoothing=smoothing if wandering else 0.0,
    )
    for k, pose in same.world_from_body.items():
        np.testing.assert_array_equal(gated.world_from_body[k], pose)
    assert gated.summary()["imu_accel_walk_factor"] == gated.imu_walk_factors[0]


def test_bias_smoothing_keeps_a_loose_walk_from_loosening_the_imu_factors() -> None:
    """``GlobalBaParams.imu_accel_bias_smoothing``: 24 s of the monocular problem with the
    wandering accelerometer bias. A walk x1000 inside ``CombinedImuFactor``s also widens their
    preintegrated noise, and the IMU loses its hold on the map's scale; with the smoothing the
    same walk is a factor of its own beside ``ImuFactor``s and the bias a second-order walk,
    and the scale holds."""
    num_kf = 96
    problem = _mono_problem(num_kf=num_kf, seed=7, num_points=3000, accel_offset_m_s2=_bias_wander)

    def scale_error(smoothing: float) -> float:
        error, factors = _adjusted(
            problem,
            imu_midpoint_rotation=True,
            imu_accel_walk_factor=1000.0,
            imu_accel_bias_smoothing=smoothing,
        )
        assert factors == num_kf - 1
        return error

    combined, smoothed = scale_error(0.0), scale_error(0.015)
    # measured: 0.98 % in CombinedImuFactors, 0.21 % with the smoothing
    assert smoothed < 0.5 * combined, (smoothed, combined)

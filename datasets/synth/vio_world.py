"""A small simulated visual-inertial world for back-end tests and benchmarks (no images).

Not the synthetic *sequence* (``generator``): it produces exactly what the back end consumes,
from an analytic ground truth: the generator's IMU simulation (``imu_sim``: EuRoC noise, biases
with random walk) along a flight in a room (a ``trajectories.ProfileMotion``), and ``Keyframe``
messages whose observations are exact projections of landmarks on the walls of a room (plus
pixel noise) through EuRoC's rig without distortion, tracked across keyframes like a front end
would, with a drifting "VO" pose and noisy VO landmark positions as initial guesses. The VO
frame is the first keyframe's body frame (as a VO front end would choose), so it is not gravity
aligned.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from datasets.rigs import euroc_like_calibration
from datasets.synth.imu_sim import ImuEffects, SimulatedImu, simulate_imu
from datasets.synth.trajectories import ProfileMotion, SinusoidChannel, TimeWarp
from slam.core.calibration import Calibration, CameraIntrinsics
from slam.core.geometry import invert_transform, make_transform, transform_points
from slam.core.messages import ImuBatch, ImuSample, Keyframe


def room_flight(start_s: float = 0.0, still_s: float = 0.0, ramp_s: float = 2.0) -> ProfileMotion:
    """A smooth flight in the room: a wobbling 1.5 x 1.2 m ellipse at 1.5 m height (0.5 rad/s,
    about 4 s per radian), looking outwards and rolling a little.

    The path is entered at path time ``start_s``; ``still_s`` > 0 holds the vehicle still that
    long, then ramps smoothly into motion over ``ramp_s`` (the generator's ``TimeWarp``).
    """

    def channel(*terms: tuple[float, float, float], c0: float = 0.0, c1: float = 0.0):
        """c0 + c1 u + sum a sin(w u + phi) at path time u = start_s + s."""
        return SinusoidChannel(
            c0=c0 + c1 * start_s,
            c1=c1,
            terms=tuple((a, w, phi + w * start_s) for a, w, phi in terms),
        )

    omega, phase, half_pi = 0.5, 0.3, 0.5 * np.pi
    return ProfileMotion(
        name="vio-room",
        x=channel((1.5, omega, phase + half_pi), (0.15, 1.7, 0.0)),
        y=channel((1.2, omega, phase), (0.1, 2.3, half_pi)),
        z=channel((0.3, 0.8, 0.0), (0.05, 3.1, 0.0), c0=1.5),
        yaw=channel((0.4, 0.6, 0.0), c0=phase, c1=omega),
        pitch=channel((0.12, 1.1, 0.5)),
        roll=channel((0.1, 1.3, 0.0)),
        warp=TimeWarp(still_s, ramp_s) if still_s > 0.0 else TimeWarp(0.0, 0.0),
    )


def room_landmarks(
    rng: np.random.Generator, count: int = 4000, half_size_m: float = 6.0, height_m: float = 4.0
) -> np.ndarray:
    """Points on the four walls, floor and ceiling of a box room, (count, 3)."""
    pts = np.zeros((count, 3))
    face = rng.integers(0, 6, count)
    u = rng.uniform(-half_size_m, half_size_m, count)
    v = rng.uniform(0.0, height_m, count)
    w = rng.uniform(-half_size_m, half_size_m, count)
    for f, (axis, val) in enumerate([(0, -1), (0, 1), (1, -1), (1, 1)]):
        m = face == f
        pts[m, axis] = val * half_size_m
        pts[m, 1 - axis] = u[m]
        pts[m, 2] = v[m]
    m = face >= 4
    pts[m, 0] = u[m]
    pts[m, 1] = w[m]
    pts[m, 2] = np.where(face[m] == 4, 0.0, height_m)
    return pts


@dataclass(frozen=True, eq=False)
class SimWorld:
    """Everything a back-end test needs, with the truth to compare against."""

    calibration: Calibration
    trajectory: ProfileMotion  # trajectory time 0 = message time 1 s
    imu: SimulatedImu  # message times, and the true biases
    keyframes: list[Keyframe]
    landmarks_world: np.ndarray  # (L, 3) truth, landmark id = row index
    world_from_body_gt: np.ndarray  # (K, 4, 4) truth at keyframe times
    vo_from_world: np.ndarray  # (4, 4) the VO frame used by the simulated front end

    def messages(self) -> list[ImuSample | Keyframe]:
        """IMU samples and keyframes merged in time order (IMU first at equal times)."""
        out: list[tuple[int, int, ImuSample | Keyframe]] = []
        imu = self.imu.arrays
        for s in ImuBatch(imu.t_ns, imu.gyro_rad_s, imu.accel_m_s2).samples():
            out.append((s.t_ns, 0, s))
        for kf in self.keyframes:
            out.append((kf.t_ns, 1, kf))
        out.sort(key=lambda x: (x[0], x[1]))
        return [m for _, _, m in out]


def _project(
    cam_from_world: np.ndarray, k: CameraIntrinsics, pts_w: np.ndarray, min_depth_m: float
) -> tuple[np.ndarray, np.ndarray]:
    pc = transform_points(cam_from_world, pts_w)
    z = pc[:, 2]
    ok = z > min_depth_m
    uv = np.full((len(pts_w), 2), np.nan)
    uv[ok, 0] = k.fx * pc[ok, 0] / z[ok] + k.cx
    uv[ok, 1] = k.fy * pc[ok, 1] / z[ok] + k.cy
    inside = ok & (uv[:, 0] >= 0) & (uv[:, 0] < k.width) & (uv[:, 1] >= 0) & (uv[:, 1] < k.height)
    inside &= z < 20.0
    return uv, inside


def generate_world(
    duration_s: float = 30.0,
    seed: int = 0,
    start_s: float = 0.0,
    keyframe_rate_hz: float = 10.0,
    landmarks_per_keyframe: int = 150,
    pixel_sigma_px: float = 0.5,
    imu_noise: bool = True,
    vo_step_sigma_m: float = 0.002,
    vo_step_sigma_rad: float = 0.0005,
    vo_point_sigma_m: float = 0.02,
    still_s: float = 0.0,
    imu_effects: ImuEffects | None = None,
) -> SimWorld:
    """A deterministic world (per seed); message time starts at 1 s (trajectory time 0).

    ``start_s`` is where on the analytic path the flight starts (in motion unless ``still_s`` >
    0, which holds the vehicle still for that long and then ramps smoothly into motion).
    ``imu_effects``: scale errors, misalignment, vibration of the IMU (``imu.distortion``)."""
    rng = np.random.default_rng(seed)
    calib = euroc_like_calibration(distortion=False)  # no images: ideal lenses
    imu_cal = calib.imu
    assert imu_cal is not None
    traj = room_flight(start_s=start_s, still_s=still_s)
    t0_ns = 1_000_000_000
    dt_ns = int(round(1e9 / imu_cal.rate_hz))
    total_s = still_s + duration_s
    t_imu_ns = t0_ns + np.arange(0, int(total_s * 1e9) + dt_ns, dt_ns, dtype=np.int64)

    def traj_time(t_ns: np.ndarray) -> np.ndarray:
        return (t_ns - t0_ns).astype(np.float64) * 1e-9

    imu = simulate_imu(
        traj,
        t_imu_ns,
        0.0,  # trajectory time at the first sample
        imu_cal,
        noise=imu_noise,
        seed=int(rng.integers(2**63)),
        gyro_bias0_rad_s=np.array([-0.0022, 0.0215, 0.077]),  # EuRoC V1_01's ground truth
        accel_bias0_m_s2=np.array([-0.018, 0.066, 0.031]),
        effects=imu_effects,
    )

    landmarks = room_landmarks(rng)
    kf_dt_ns = int(round(1e9 / keyframe_rate_hz))
    t_kf_ns = np.arange(t0_ns + 2_500_000, t_imu_ns[-1] - dt_ns, kf_dt_ns, dtype=np.int64)
    w_from_b = traj.sample(traj_time(t_kf_ns)).world_from_body()
    vo_from_world = invert_transform(w_from_b[0])
    cams = calib.cameras
    keyframes: list[Keyframe] = []
    active: np.ndarray = np.zeros(0, dtype=np.int64)
    drift = np.eye(4)
    for k, t_ns in enumerate(t_kf_ns):
        cam_from_world = [invert_transform(w_from_b[k] @ c.body_from_cam) for c in cams]
        uv_l, in_l = _project(cam_from_world[0], cams[0].intrinsics, landmarks, 0.3)
        uv_r, in_r = _project(cam_from_world[1], cams[1].intrinsics, landmarks, 0.3)
        visible = np.flatnonzero(in_l)
        keep = active[np.isin(active, visible)]
        new = np.setdiff1d(visible, keep)
        rng.shuffle(new)
        ids = np.concatenate([keep, new])[:landmarks_per_keyframe].astype(np.int64)
        active = ids
        pl = uv_l[ids] + rng.normal(0, pixel_sigma_px, (len(ids), 2))
        pr = uv_r[ids] + rng.normal(0, pixel_sigma_px, (len(ids), 2))
        pr[~in_r[ids]] = np.nan
        if k > 0:
            step = make_transform(
                Rotation.from_rotvec(rng.normal(0, vo_step_sigma_rad, 3)).as_matrix(),
                rng.normal(0, vo_step_sigma_m, 3),
            )
            drift = drift @ step
        vo_pose = vo_from_world @ w_from_b[k] @ drift
        pts_vo = transform_points(vo_from_world, landmarks[ids]) + rng.normal(
            0, vo_point_sigma_m, (len(ids), 3)
        )
        keyframes.append(
            Keyframe(
                t_ns=int(t_ns),
                keyframe_id=k,
                frame_index=2 * k,
                segment_id=0,
                world_from_body_vo=vo_pose,
                landmark_ids=ids,
                pixels_left_undist=pl,
                pixels_right_undist=pr,
                points_world_vo=pts_vo,
                image_left=np.zeros((1, 1), np.uint8),
                image_right=None,
            )
        )
    return SimWorld(calib, traj, imu, keyframes, landmarks, w_from_b, vo_from_world)

"""A small simulated visual-inertial world for back-end tests and benchmarks.

Not the project's synthetic *sequence* generator (no images are rendered): it produces exactly
what the back end consumes, from an analytic ground truth: an IMU stream (EuRoC noise, biases
with random walk) and ``Keyframe`` messages whose observations are exact projections of landmarks
on the walls of a room (plus pixel noise), tracked across keyframes like a front end would, with
a drifting "VO" pose and noisy VO landmark positions as initial guesses. The VO frame is the
first keyframe's body frame (as a VO front end would choose), so it is not gravity aligned.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from datasets.rigs import euroc_like_calibration
from slam.calibration import Calibration, CameraIntrinsics, ImuCalibration
from slam.geometry import invert_transform, make_transform, transform_points
from slam.messages import ImuSample, Keyframe

GRAVITY_M_S2 = 9.81

# EuRoC's IMU x axis points up when level, its cameras look along body +z: body axes in world.
_R_LEVEL = np.array([[0.0, 0.0, 1.0], [0.0, -1.0, 0.0], [1.0, 0.0, 0.0]])


@dataclass(frozen=True)
class RoomTrajectory:
    """Smooth analytic flight in a room: a wobbling ellipse, looking outwards, rolling a little."""

    radius_x_m: float = 1.5
    radius_y_m: float = 1.2
    height_m: float = 1.5
    omega_rad_s: float = 0.5
    phase_rad: float = 0.3
    start_s: float = 0.0  # path parameter at time 0
    still_s: float = 0.0  # held still this long, then ramps into motion
    ramp_s: float = 2.0  # the ramp's length (path speed goes 0 -> 1 with zero end accelerations)

    def _warp(self, t_s: np.ndarray) -> np.ndarray:
        """Time -> path parameter: C2 ramp from rest (tau' = (1 - cos(pi u / T)) / 2)."""
        t = np.asarray(t_s, dtype=float)
        if self.still_s <= 0.0:
            return self.start_s + t
        u = np.maximum(t - self.still_s, 0.0)
        r = self.ramp_s
        in_ramp = u / 2 - r / (2 * np.pi) * np.sin(np.pi * np.minimum(u, r) / r)
        return self.start_s + np.where(u < r, in_ramp, r / 2 + (u - r))

    def _angle(self, t_s: np.ndarray) -> np.ndarray:
        return self.omega_rad_s * t_s + self.phase_rad

    def position(self, t_s: np.ndarray) -> np.ndarray:
        t = self._warp(t_s)
        th = self._angle(t)
        return np.stack(
            [
                self.radius_x_m * np.cos(th) + 0.15 * np.sin(1.7 * t),
                self.radius_y_m * np.sin(th) + 0.1 * np.cos(2.3 * t),
                self.height_m + 0.3 * np.sin(0.8 * t) + 0.05 * np.sin(3.1 * t),
            ],
            axis=-1,
        )

    def rotation(self, t_s: np.ndarray) -> np.ndarray:
        """(N, 3, 3) world_from_body rotations."""
        t = np.atleast_1d(self._warp(t_s))
        yaw = self._angle(t) + 0.4 * np.sin(0.6 * t)
        pitch = 0.12 * np.sin(1.1 * t + 0.5)
        roll = 0.1 * np.sin(1.3 * t)
        r = Rotation.from_euler("ZYX", np.stack([yaw, pitch, roll], axis=1)).as_matrix()
        return r @ _R_LEVEL

    def world_from_body(self, t_s: np.ndarray) -> np.ndarray:
        t = np.atleast_1d(np.asarray(t_s, dtype=float))
        out = np.zeros((len(t), 4, 4))
        out[:, :3, :3] = self.rotation(t)
        out[:, :3, 3] = self.position(t)
        out[:, 3, 3] = 1.0
        return out

    def velocity(self, t_s: np.ndarray, h: float = 1e-4) -> np.ndarray:
        t = np.asarray(t_s, dtype=float)
        return (self.position(t + h) - self.position(t - h)) / (2 * h)

    def acceleration(self, t_s: np.ndarray, h: float = 1e-3) -> np.ndarray:
        t = np.asarray(t_s, dtype=float)
        return (self.position(t + h) - 2 * self.position(t) + self.position(t - h)) / (h * h)

    def body_rate(self, t_s: np.ndarray, h: float = 1e-4) -> np.ndarray:
        """Angular velocity in the body frame (rad/s), central difference on SO(3)."""
        t = np.atleast_1d(np.asarray(t_s, dtype=float))
        r0 = self.rotation(t - h)
        r1 = self.rotation(t + h)
        rel = np.einsum("nji,njk->nik", r0, r1)
        return Rotation.from_matrix(rel).as_rotvec() / (2 * h)


@dataclass(frozen=True, eq=False)
class SimImu:
    """Simulated IMU stream and the true biases at every sample."""

    t_ns: np.ndarray
    gyro_rad_s: np.ndarray
    accel_m_s2: np.ndarray
    bias_gyro_rad_s: np.ndarray  # (N, 3) truth
    bias_accel_m_s2: np.ndarray  # (N, 3) truth

    def samples(self) -> list[ImuSample]:
        return [
            ImuSample(int(self.t_ns[i]), self.gyro_rad_s[i], self.accel_m_s2[i])
            for i in range(len(self.t_ns))
        ]


def simulate_imu(
    traj: RoomTrajectory,
    t_ns: np.ndarray,
    imu: ImuCalibration,
    rng: np.random.Generator,
    bias_gyro0_rad_s: np.ndarray,
    bias_accel0_m_s2: np.ndarray,
    noise: bool = True,
) -> SimImu:
    """Readings at ``t_ns``: gyro = ω_body + b_g + n, accel = R^T (a - g_world) + b_a + n."""
    t_s = t_ns.astype(np.float64) * 1e-9
    rot = traj.rotation(t_s)
    acc_w = traj.acceleration(t_s) + np.array([0.0, 0.0, imu.gravity_m_s2])
    accel = np.einsum("nji,nj->ni", rot, acc_w)
    gyro = traj.body_rate(t_s)
    n = len(t_ns)
    dt = 1.0 / imu.rate_hz
    if noise:
        bg = bias_gyro0_rad_s + np.cumsum(
            rng.normal(0, imu.gyro_random_walk * np.sqrt(dt), (n, 3)), 0
        )
        ba = bias_accel0_m_s2 + np.cumsum(
            rng.normal(0, imu.accel_random_walk * np.sqrt(dt), (n, 3)), 0
        )
        gyro = gyro + bg + rng.normal(0, imu.gyro_noise_density / np.sqrt(dt), (n, 3))
        accel = accel + ba + rng.normal(0, imu.accel_noise_density / np.sqrt(dt), (n, 3))
    else:
        bg = np.tile(bias_gyro0_rad_s, (n, 1))
        ba = np.tile(bias_accel0_m_s2, (n, 1))
        gyro, accel = gyro + bg, accel + ba
    return SimImu(t_ns, gyro, accel, bg, ba)


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
    trajectory: RoomTrajectory
    imu: SimImu
    keyframes: list[Keyframe]
    landmarks_world: np.ndarray  # (L, 3) truth, landmark id = row index
    world_from_body_gt: np.ndarray  # (K, 4, 4) truth at keyframe times
    vo_from_world: np.ndarray  # (4, 4) the VO frame used by the simulated front end

    def messages(self) -> list[ImuSample | Keyframe]:
        """IMU samples and keyframes merged in time order (IMU first at equal times)."""
        out: list[tuple[int, int, ImuSample | Keyframe]] = []
        for s in self.imu.samples():
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
) -> SimWorld:
    """A deterministic world (per seed); message time starts at 1 s (trajectory time 0).

    ``start_s`` is where on the analytic path the flight starts (in motion unless ``still_s`` >
    0, which holds the vehicle still for that long and then ramps smoothly into motion)."""
    rng = np.random.default_rng(seed)
    calib = euroc_like_calibration(distortion=False)  # no images: ideal lenses
    imu_cal = calib.imu
    assert imu_cal is not None
    traj = RoomTrajectory(start_s=start_s, still_s=still_s)
    t0_ns = 1_000_000_000
    dt_ns = int(round(1e9 / imu_cal.rate_hz))
    total_s = still_s + duration_s
    t_imu_ns = t0_ns + np.arange(0, int(total_s * 1e9) + dt_ns, dt_ns, dtype=np.int64)

    def traj_time(t_ns: np.ndarray) -> np.ndarray:
        return (t_ns - t0_ns).astype(np.float64) * 1e-9

    bg0 = np.array([-0.0022, 0.0215, 0.077])  # EuRoC V1_01's ground-truth biases
    ba0 = np.array([-0.018, 0.066, 0.031])
    sim = simulate_imu(traj, t_imu_ns - t0_ns, imu_cal, rng, bg0, ba0, imu_noise)
    sim = SimImu(t_imu_ns, sim.gyro_rad_s, sim.accel_m_s2, sim.bias_gyro_rad_s, sim.bias_accel_m_s2)

    landmarks = room_landmarks(rng)
    kf_dt_ns = int(round(1e9 / keyframe_rate_hz))
    t_kf_ns = np.arange(t0_ns + 2_500_000, t_imu_ns[-1] - dt_ns, kf_dt_ns, dtype=np.int64)
    w_from_b = traj.world_from_body(traj_time(t_kf_ns))
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
    return SimWorld(calib, traj, sim, keyframes, landmarks, w_from_b, vo_from_world)


def align_se3(est_positions: np.ndarray, gt_positions: np.ndarray) -> np.ndarray:
    """Umeyama (no scale): the 4x4 gt_from_est minimising the position error."""
    mu_e = est_positions.mean(axis=0)
    mu_g = gt_positions.mean(axis=0)
    cov = (gt_positions - mu_g).T @ (est_positions - mu_e)
    u, _, vt = np.linalg.svd(cov)
    d = np.eye(3)
    d[2, 2] = np.sign(np.linalg.det(u @ vt))
    rot = u @ d @ vt
    return make_transform(rot, mu_g - rot @ mu_e)


def ate_se3_rmse(est_positions: np.ndarray, gt_positions: np.ndarray) -> float:
    """Absolute trajectory error (RMSE, m) after SE(3) alignment."""
    t = align_se3(est_positions, gt_positions)
    err = transform_points(t, est_positions) - gt_positions
    return float(np.sqrt(np.mean(np.sum(err**2, axis=1))))

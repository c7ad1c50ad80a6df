"""Run outputs, always written atomically (temp file in the same folder, then rename).

- ``trajectory.tum``: ``t[s] x y z qx qy qz qw`` world_from_body (body = IMU frame); TUM files
  store the quaternion x,y,z,w and time in seconds.
- ``trajectory.csv``: EuRoC ground-truth layout (ns, position, q w,x,y,z).
- ``keyframes.tum``, ``stats.json``, ``config.yaml``.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np

from slam.atomic import write_atomic
from slam.trajectory import Trajectory


def tum_text(traj: Trajectory) -> str:
    lines = ["# timestamp[s] tx ty tz qx qy qz qw  (world_from_body, body = IMU)"]
    q = traj.q_wxyz
    for i in range(len(traj)):
        t_ns = int(traj.t_ns[i])
        p = traj.positions_m[i]
        # exact decimal seconds from integer ns: no float rounding of the timestamp
        lines.append(
            f"{t_ns // 1_000_000_000}.{t_ns % 1_000_000_000:09d} "
            f"{p[0]:.9f} {p[1]:.9f} {p[2]:.9f} "
            f"{q[i, 1]:.9f} {q[i, 2]:.9f} {q[i, 3]:.9f} {q[i, 0]:.9f}"  # TUM stores x,y,z,w
        )
    return "\n".join(lines) + "\n"


def euroc_csv_text(traj: Trajectory) -> str:
    lines = [
        "#timestamp [ns],p_RS_R_x [m],p_RS_R_y [m],p_RS_R_z [m],"
        "q_RS_w [],q_RS_x [],q_RS_y [],q_RS_z []"
    ]
    for i in range(len(traj)):
        p = traj.positions_m[i]
        q = traj.q_wxyz[i]
        lines.append(
            f"{int(traj.t_ns[i])},{p[0]:.9f},{p[1]:.9f},{p[2]:.9f},"
            f"{q[0]:.9f},{q[1]:.9f},{q[2]:.9f},{q[3]:.9f}"
        )
    return "\n".join(lines) + "\n"


def empty_trajectory() -> Trajectory:
    return Trajectory(np.zeros(0, np.int64), np.zeros((0, 3)), np.zeros((0, 4)))


def trajectory_from_poses(poses: list[tuple[int, np.ndarray]]) -> Trajectory:
    """(t_ns, world_from_body) pairs -> Trajectory."""
    if not poses:
        return empty_trajectory()
    t = np.array([p[0] for p in poses], dtype=np.int64)
    mats = np.stack([p[1] for p in poses])
    return Trajectory.from_matrices(t, mats)


def write_run_outputs(
    out_dir: Path,
    trajectory: Trajectory,
    keyframes: Trajectory,
    stats: dict[str, Any],
    config_yaml: str,
    extra_trajectories: dict[str, Trajectory] | None = None,
) -> None:
    out_dir = Path(out_dir)
    write_atomic(out_dir / "trajectory.tum", tum_text(trajectory))
    write_atomic(out_dir / "trajectory.csv", euroc_csv_text(trajectory))
    write_atomic(out_dir / "keyframes.tum", tum_text(keyframes))
    for name, traj in (extra_trajectories or {}).items():
        write_atomic(out_dir / f"{name}.tum", tum_text(traj))
    write_atomic(out_dir / "stats.json", json.dumps(stats, indent=2, default=float) + "\n")
    write_atomic(out_dir / "config.yaml", config_yaml)

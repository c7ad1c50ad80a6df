"""Run outputs, always written atomically (temp file in the same folder, then rename).

- ``trajectory.tum``: ``t[s] x y z qx qy qz qw`` world_from_body (body = IMU frame); TUM files
  store the quaternion x,y,z,w and time in seconds. The live pose as published, in the
  loop-corrected map; ``trajectory_odometry.tum`` the odometry, ``trajectory_loop_closed.tum``
  the final estimate (extra trajectories).
- ``trajectory.csv``: EuRoC ground-truth layout (ns, position, q w,x,y,z).
- ``keyframes.tum``, ``stats.json``, ``config.yaml``.

Trajectories go through the one TUM / EuRoC csv writer, :mod:`slam.evaluation.io`: exact decimal
times from the integer ns, every other value lossless (shortest round-trip float64 ``repr``).
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np

from slam.core.atomic import write_atomic
from slam.core.trajectory import Trajectory
from slam.evaluation.io import write_euroc_csv, write_tum

#: The comment line of the run's TUM files (after the '#').
RUN_TUM_HEADER = "timestamp[s] tx ty tz qx qy qz qw  (world_from_body, body = IMU)"


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
    write_tum(out_dir / "trajectory.tum", trajectory, RUN_TUM_HEADER)
    write_euroc_csv(out_dir / "trajectory.csv", trajectory)
    write_tum(out_dir / "keyframes.tum", keyframes, RUN_TUM_HEADER)
    for name, traj in (extra_trajectories or {}).items():
        write_tum(out_dir / f"{name}.tum", traj, RUN_TUM_HEADER)
    write_atomic(out_dir / "stats.json", json.dumps(stats, indent=2, default=float) + "\n")
    write_atomic(out_dir / "config.yaml", config_yaml)

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
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from slam.core.atomic import write_atomic
from slam.core.trajectory import Trajectory
from slam.evaluation.io import (
    EUROC_HEADER,
    euroc_times,
    euroc_values,
    text_rows,
    tum_times,
    tum_values,
)

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


class RunOutputs:
    """Writes a run's outputs into ``out_dir``, again and again during the run (every few
    seconds, ``slam.runtime.report``) and once at its end.

    The text of a trajectory's rows that are the same as at the last write (its first rows: the
    live and odometry trajectories only grow) is reused rather than formatted again: formatting
    every row took 45-185 ms of Python per write on the hall's 2,800 frames, in the player's
    thread, and every millisecond of it the front end's thread waits for the GIL at each of its
    OpenCV calls. The files are the same as :func:`slam.evaluation.io.write_tum` and
    ``write_euroc_csv`` write. ``config_yaml`` does not change during a run: written once."""

    def __init__(self, out_dir: Path, config_yaml: str):
        self.out_dir = Path(out_dir)
        self._config_yaml: str | None = config_yaml
        self._rows: dict[str, tuple[np.ndarray, np.ndarray, list[str]]] = {}

    def write(
        self,
        trajectory: Trajectory,
        keyframes: Trajectory,
        stats: dict[str, Any],
        extra_trajectories: dict[str, Trajectory] | None = None,
    ) -> None:
        self._write_tum("trajectory.tum", trajectory)
        self._write_csv("trajectory.csv", trajectory)
        self._write_tum("keyframes.tum", keyframes)
        for name, traj in (extra_trajectories or {}).items():
            self._write_tum(f"{name}.tum", traj)
        write_atomic(self.out_dir / "stats.json", json.dumps(stats, indent=2, default=float) + "\n")
        if self._config_yaml is not None:
            write_atomic(self.out_dir / "config.yaml", self._config_yaml)
            self._config_yaml = None

    def _write_tum(self, name: str, traj: Trajectory) -> None:
        rows = self._text_rows(name, traj.t_ns, tum_values(traj), tum_times, " ")
        write_atomic(self.out_dir / name, "\n".join([f"# {RUN_TUM_HEADER}", *rows]) + "\n")

    def _write_csv(self, name: str, traj: Trajectory) -> None:
        rows = self._text_rows(name, traj.t_ns, euroc_values(traj), euroc_times, ",")
        write_atomic(self.out_dir / name, "\n".join([f"#{EUROC_HEADER}", *rows]) + "\n")

    def _text_rows(
        self,
        name: str,
        t_ns: np.ndarray,
        values: np.ndarray,
        times: Callable[[np.ndarray], list[str]],
        sep: str,
    ) -> list[str]:
        """The rows' lines of file ``name``: those of its unchanged first rows as last time,
        the rest formatted."""
        bits = np.ascontiguousarray(values, dtype=np.float64).view(np.int64)  # -0.0, nan: exact
        same = 0
        if name in self._rows:
            old_t, old_v, old_rows = self._rows[name]
            n = min(len(old_t), len(t_ns))
            differs = (old_t[:n] != t_ns[:n]) | (old_v[:n] != bits[:n]).any(axis=1)
            same = int(np.argmax(differs)) if differs.any() else n
            rows = old_rows[:same]
        else:
            rows = []
        rows += text_rows(times(t_ns[same:]), values[same:], sep)
        self._rows[name] = (t_ns.copy(), bits.copy(), rows)
        return rows

"""The trajectory type shared by ground truth, estimates and evaluation."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from slam.core.geometry import matrix_to_quat_wxyz, poses_to_matrices


@dataclass(frozen=True, eq=False)
class Trajectory:
    """Timestamped poses world_from_body.

    ``t_ns`` int64 nanoseconds (strictly increasing), ``positions_m`` (N, 3),
    ``q_wxyz`` (N, 4) unit quaternions, scalar first.
    """

    t_ns: np.ndarray
    positions_m: np.ndarray
    q_wxyz: np.ndarray

    def __post_init__(self) -> None:
        n = len(self.t_ns)
        if self.positions_m.shape != (n, 3) or self.q_wxyz.shape != (n, 4):
            raise ValueError(
                f"trajectory arrays disagree: t {self.t_ns.shape}, "
                f"positions {self.positions_m.shape}, quaternions {self.q_wxyz.shape}"
            )

    def __len__(self) -> int:
        return len(self.t_ns)

    @property
    def t_s(self) -> np.ndarray:
        """Timestamps in seconds (float64), for I/O and plots."""
        return self.t_ns.astype(np.float64) * 1e-9

    def matrices(self) -> np.ndarray:
        """(N, 4, 4) world_from_body."""
        return poses_to_matrices(self.positions_m, self.q_wxyz)

    @staticmethod
    def from_matrices(t_ns: np.ndarray, world_from_body: np.ndarray) -> Trajectory:
        return Trajectory(
            t_ns=np.asarray(t_ns, dtype=np.int64),
            positions_m=np.ascontiguousarray(world_from_body[:, :3, 3], dtype=float),
            q_wxyz=matrix_to_quat_wxyz(world_from_body[:, :3, :3]),
        )

    def path_length_m(self) -> float:
        if len(self) < 2:
            return 0.0
        return float(np.linalg.norm(np.diff(self.positions_m, axis=0), axis=1).sum())

    def slice(self, mask_or_index: np.ndarray | slice) -> Trajectory:
        return Trajectory(
            t_ns=self.t_ns[mask_or_index],
            positions_m=self.positions_m[mask_or_index],
            q_wxyz=self.q_wxyz[mask_or_index],
        )

"""The run's outputs written again and again (RunOutputs): the same files as the one writer's."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from slam.core.trajectory import Trajectory
from slam.evaluation.io import euroc_csv_text, tum_text
from slam.runtime.outputs import RUN_TUM_HEADER, RunOutputs


def _trajectory(n: int, seed: int) -> Trajectory:
    rng = np.random.default_rng(seed)
    q = rng.normal(size=(n, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    return Trajectory(np.arange(n, dtype=np.int64) * 50_000_001, rng.normal(size=(n, 3)), q)


def _rows(traj: Trajectory, rows: slice) -> Trajectory:
    return Trajectory(traj.t_ns[rows], traj.positions_m[rows], traj.q_wxyz[rows])


def test_rewrites_are_the_files_written_from_scratch(tmp_path: Path) -> None:
    out = RunOutputs(tmp_path, "preset: x\n")
    full = _trajectory(40, 0)
    changed = _trajectory(40, 1)  # a loop correction moved the rows from 25 on
    changed = Trajectory(
        full.t_ns,
        np.vstack([full.positions_m[:25], changed.positions_m[25:]]),
        np.vstack([full.q_wxyz[:25], changed.q_wxyz[25:]]),
    )
    signed_zero = Trajectory(full.t_ns, full.positions_m.copy(), full.q_wxyz)
    signed_zero.positions_m[3, 0] = 0.0
    negative_zero = Trajectory(full.t_ns, signed_zero.positions_m.copy(), full.q_wxyz)
    negative_zero.positions_m[3, 0] = -0.0  # equal as floats, not as text
    for traj in (
        _rows(full, slice(0, 10)),  # grows
        _rows(full, slice(0, 30)),
        changed,  # rows changed in the middle
        _rows(full, slice(0, 20)),  # shorter
        _rows(full, slice(0, 0)),
        signed_zero,
        negative_zero,
    ):
        out.write(traj, _rows(traj, slice(0, None, 5)), {"n": len(traj)}, {"extra": traj})
        assert (tmp_path / "trajectory.tum").read_text() == tum_text(traj, RUN_TUM_HEADER)
        assert (tmp_path / "extra.tum").read_text() == tum_text(traj, RUN_TUM_HEADER)
        assert (tmp_path / "trajectory.csv").read_text() == euroc_csv_text(traj)
        keyframes = _rows(traj, slice(0, None, 5))
        assert (tmp_path / "keyframes.tum").read_text() == tum_text(keyframes, RUN_TUM_HEADER)
        assert (tmp_path / "config.yaml").read_text() == "preset: x\n"

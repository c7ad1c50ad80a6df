"""posyaw alignment, interpolation and segment drift against analytic ground truth; the CLI end to end."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from slam.core.trajectory import Trajectory
from slam.evaluation import evaluate as ev
from slam.evaluation import io as evio
from slam.evaluation import lie
from slam.evaluation.align import estimate_alignment
from tools.cli import main


def _helix(n: int = 400, dt_ns: int = 50_000_000, t0_ns: int = 1_000_000_000_000) -> Trajectory:
    t = np.arange(n) * dt_ns * 1e-9
    pos = np.column_stack([np.cos(0.5 * t) * 3, np.sin(0.5 * t) * 2, 0.1 * t + 0.3 * np.sin(t)])
    yaw, pitch = 0.5 * t + 1.0, 0.2 * np.sin(0.7 * t)
    q = np.column_stack(
        [
            np.cos(yaw / 2) * np.cos(pitch / 2),
            -np.sin(yaw / 2) * np.sin(pitch / 2),
            np.cos(yaw / 2) * np.sin(pitch / 2),
            np.sin(yaw / 2) * np.cos(pitch / 2),
        ]
    )
    return Trajectory(
        t0_ns + np.arange(n, dtype=np.int64) * dt_ns, pos, q / np.linalg.norm(q, axis=1)[:, None]
    )


def _source(traj: Trajectory, name: str) -> evio.PoseSource:
    return evio.PoseSource(
        traj, lie.poses_from_pq(traj.positions_m, traj.q_wxyz), name, name, "tum"
    )


def _transformed(traj: Trajectory, rotation: np.ndarray, translation: np.ndarray) -> Trajectory:
    m = lie.poses_from_pq(traj.positions_m, traj.q_wxyz)
    t = np.eye(4)
    t[:3, :3], t[:3, 3] = rotation, translation
    out = t @ m
    return Trajectory(traj.t_ns, out[:, :3, 3].copy(), lie.matrices_to_quat_wxyz(out[:, :3, :3]))


def test_posyaw_recovers_a_known_4dof_offset() -> None:
    gt = _helix()
    yaw = 0.7
    est = _transformed(gt, lie.yaw_rotation(-yaw), np.array([4.0, -2.0, 0.5]))  # est = T^-1-ish
    p = ev.prepare(_source(gt, "gt"), _source(est, "est"), ev.EvalOptions(align="posyaw"))
    a = p.alignment
    assert a.rotation == pytest.approx(lie.yaw_rotation(yaw), abs=1e-12)
    res = ev.ape_of(p, "trans")
    assert res.stats["max"] < 1e-12
    assert ev.ape_of(p, "angle_deg").stats["max"] < 1e-9
    # a roll/pitch offset is not something posyaw can absorb: errors stay, se3 removes them
    tilted = _transformed(
        gt,
        lie.quat_wxyz_to_matrices(np.array([[np.cos(0.05), np.sin(0.05), 0, 0]]))[0],
        np.zeros(3),
    )
    p2 = ev.prepare(_source(gt, "gt"), _source(tilted, "t"), ev.EvalOptions(align="posyaw"))
    assert ev.ape_of(p2, "trans").stats["rmse"] > 1e-3
    p3 = ev.prepare(_source(gt, "gt"), _source(tilted, "t"), ev.EvalOptions(align="se3"))
    assert ev.ape_of(p3, "trans").stats["max"] < 1e-9


def test_sim3_and_first_n() -> None:
    gt = _helix()
    m = lie.poses_from_pq(gt.positions_m, gt.q_wxyz)
    est_pos = 0.5 * m[:, :3, 3] + np.array([1.0, 2.0, 3.0])
    est = Trajectory(gt.t_ns, est_pos, gt.q_wxyz)
    a = estimate_alignment(m, lie.poses_from_pq(est.positions_m, est.q_wxyz), "sim3", 50)
    assert a.scale == pytest.approx(2.0, rel=1e-12) and a.n_used == 50


def test_interpolation_is_exact_on_linear_motion_and_constant_rotation_rate() -> None:
    n = 200
    t_ns = np.arange(n, dtype=np.int64) * 100_000_000  # 10 Hz reference
    angle = 0.3 * t_ns * 1e-9  # rad, constant rate about a fixed axis: SLERP is exact
    axis = np.array([1.0, 2.0, 2.0]) / 3.0
    q = np.column_stack([np.cos(angle / 2), np.outer(np.sin(angle / 2), axis)])
    pos = np.column_stack([0.5 * t_ns * 1e-9, -0.2 * t_ns * 1e-9, np.ones(n)])
    gt = Trajectory(t_ns, pos, q)
    t_est = np.arange(5, n * 10 - 20, 7, dtype=np.int64) * 10_000_000 + 3_000_000  # between samples
    a_est = 0.3 * t_est * 1e-9
    est = Trajectory(
        t_est,
        np.column_stack([0.5 * t_est * 1e-9, -0.2 * t_est * 1e-9, np.ones(len(t_est))]),
        np.column_stack([np.cos(a_est / 2), np.outer(np.sin(a_est / 2), axis)]),
    )
    opts = ev.EvalOptions(align="none", interpolate=True)
    p = ev.prepare(_source(gt, "gt"), _source(est, "est"), opts)
    assert len(p.association) == len(t_est)
    assert ev.ape_of(p, "trans").stats["max"] < 1e-12
    assert ev.ape_of(p, "angle_deg").stats["max"] < 1e-9
    # nearest association with the same data is off by up to half a step
    p_near = ev.prepare(
        _source(gt, "gt"), _source(est, "est"), ev.EvalOptions(align="none", max_diff_s=0.06)
    )
    assert ev.ape_of(p_near, "trans").stats["max"] > 1e-3


def test_t_offset_and_seconds_delta() -> None:
    gt = _helix()
    shifted = Trajectory(gt.t_ns - 2_000_000_000, gt.positions_m, gt.q_wxyz)  # est clock 2 s behind
    p = ev.prepare(
        _source(gt, "gt"), _source(shifted, "e"), ev.EvalOptions(align="none", t_offset_s=2.0)
    )
    assert len(p.association) == len(gt) and ev.ape_of(p).stats["max"] == 0.0
    r = ev.rpe_of(p, "trans", 1.0, "seconds")
    assert len(r.errors) == 20 and r.stats["max"] < 1e-12


def test_segment_drift_of_a_scaled_estimate() -> None:
    n = 400  # a straight line, 25 cm per step (exact in binary), so the path length equals the displacement
    t = np.arange(n, dtype=np.int64) * 50_000_000
    line = np.column_stack([0.25 * np.arange(n), np.zeros(n), np.zeros(n)])
    q = np.tile([1.0, 0.0, 0.0, 0.0], (n, 1))
    gt = Trajectory(t, line, q)
    est = Trajectory(t, line * 1.01, q)  # 1 % scale error: exactly 1 % drift
    p = ev.prepare(_source(gt, "gt"), _source(est, "e"), ev.EvalOptions(align="none"))
    for r in ev.segments_of(p, (5.0, 10.0)):
        assert r.stats["min"] == pytest.approx(1.0, rel=1e-9)
        assert r.stats["max"] == pytest.approx(1.0, rel=1e-9)
        assert r.extra["rot_deg_per_m"]["max"] < 1e-9


def test_cli_end_to_end(tmp_path: Path, capsys) -> None:
    gt = _helix()
    est = _transformed(gt, lie.yaw_rotation(0.3), np.array([1.0, 0.0, 0.0]))
    evio.write_tum(tmp_path / "gt.txt", gt)
    evio.write_tum(tmp_path / "est.txt", est)
    out = tmp_path / "ape.json"
    assert (
        main(
            [
                "eval",
                "ape",
                str(tmp_path / "gt.txt"),
                str(tmp_path / "est.txt"),
                "--align",
                "posyaw",
                "--json",
                str(out),
                "--plot",
                str(tmp_path / "ape.png"),
            ]
        )
        == 0
    )
    text = capsys.readouterr().out
    assert "alignment posyaw" in text and "scale 1.000000" in text
    data = json.loads(out.read_text())
    assert data["stats"]["rmse"] < 1e-9 and data["alignment"]["method"] == "posyaw"
    assert (tmp_path / "ape.png").stat().st_size > 10_000
    rpe_json = tmp_path / "rpe.json"
    assert (
        main(
            [
                "eval",
                "rpe",
                str(tmp_path / "gt.txt"),
                str(tmp_path / "est.txt"),
                "--delta",
                "1",
                "5",
                "--json",
                str(rpe_json),
                "--plot",
                str(tmp_path / "rpe.png"),
            ]
        )
        == 0
    )
    text = capsys.readouterr().out
    assert "no alignment (--align none): the estimate is compared as given, scale 1\n" in text
    assert "on 0 poses" not in text and "rotation 0.0000 deg" not in text
    for fmt, marker in (
        ("markdown", "| run"),
        ("csv", "run,metric,alignment,rmse"),
        ("latex", r"\begin{tabular}"),
    ):
        assert main(["eval", "table", str(out), str(rpe_json), "--format", fmt]) == 0
        table = capsys.readouterr().out
        assert marker in table and table.count("\n") >= 3


def test_the_alignment_line_says_what_was_estimated() -> None:
    gt = _helix(50)
    est = _transformed(gt, lie.yaw_rotation(0.3), np.array([1.0, 0.0, 0.0]))
    poses = lie.poses_from_pq(gt.positions_m, gt.q_wxyz)
    est_poses = lie.poses_from_pq(est.positions_m, est.q_wxyz)
    lines = {
        m: estimate_alignment(poses, est_poses, m).describe()
        for m in ("none", "origin", "scale", "se3")
    }
    assert (
        lines["none"] == "no alignment (--align none): the estimate is compared as given, scale 1"
    )
    assert lines["origin"].startswith(
        "alignment origin on 1 pose: scale 1.000000, rotation 17.1887 deg"
    )
    assert (
        lines["scale"].startswith("alignment scale on 50 poses: scale ")
        and "rotation" not in lines["scale"]
    )
    assert lines["se3"].startswith(
        "alignment se3 on 50 poses: scale 1.000000, rotation 17.1887 deg"
    )

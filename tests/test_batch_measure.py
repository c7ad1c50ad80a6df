"""The batch's accuracy figures over part of a run (``tools.batch.measure.ate_se3``)."""

from __future__ import annotations

import numpy as np

from tools.batch.measure import ate_se3


def _write_tum(path, t_s, xyz) -> None:
    rows = [f"{t:.3f} {x:.6f} {y:.6f} {z:.6f} 0 0 0 1" for t, (x, y, z) in zip(t_s, xyz)]
    path.write_text("\n".join(rows) + "\n")


def test_ate_after_a_time_is_the_rmse_of_those_poses_under_the_whole_alignment(tmp_path) -> None:
    t = np.arange(0.0, 20.0, 0.1)
    ref = np.stack([np.cos(t / 3), np.sin(t / 2), 0.1 * t], axis=1)
    rng = np.random.default_rng(1)
    noise_m = np.where(t >= 10.0, 0.006, 0.001)[:, None]  # the second half worse
    est = ref + rng.normal(0, 1, ref.shape) * noise_m
    _write_tum(tmp_path / "ref.tum", t, ref)
    _write_tum(tmp_path / "est.tum", t, est)
    whole = ate_se3(tmp_path / "ref.tum", tmp_path / "est.tum")
    before_all = ate_se3(tmp_path / "ref.tum", tmp_path / "est.tum", from_t_ns=0)
    second = ate_se3(tmp_path / "ref.tum", tmp_path / "est.tum", from_t_ns=10_000_000_000)
    first_sq = (len(t) * whole**2 - (t >= 10.0).sum() * second**2) / (t < 10.0).sum()
    assert before_all == whole
    assert second > 4 * np.sqrt(first_sq)  # the worse half is seen as worse
    assert abs(second - 0.006 * np.sqrt(3)) < 0.002
    assert ate_se3(tmp_path / "ref.tum", tmp_path / "est.tum", from_t_ns=10**12) is None


def test_scale_error_is_the_sim3_scale_of_the_live_trajectory(tmp_path) -> None:
    from tools.batch.measure import evaluate_run

    t = np.arange(0.0, 20.0, 0.1)
    ref = np.stack([np.cos(t / 3), np.sin(t / 2), 0.1 * t], axis=1)
    run = tmp_path / "run"
    run.mkdir()
    _write_tum(tmp_path / "ref.tum", t, ref)
    _write_tum(run / "trajectory.tum", t, 0.97 * ref + [0.2, -0.1, 0.0])  # 3 % short
    acc = evaluate_run(tmp_path / "ref.tum", run)
    # aligning the estimate onto the reference scales it by 1 / 0.97
    assert abs(acc["scale_error_pct"] - 100 * (1 / 0.97 - 1)) < 1e-4  # TUM rounds to 1 um
    assert acc["ate_se3_m"] > 0.01  # se3 alignment keeps the scale error in the ATE


def test_loop_closed_scale_error_separates_scale_from_shape(tmp_path) -> None:
    """A loop-closed trajectory of the right shape but 1 % large (a monocular map whose scale
    only the odometry held) has a loop-closed ATE of several mm under se3 alignment, all of it
    scale: its loop-closed scale error is 1 % while the live one is measured apart."""
    from tools.batch.measure import evaluate_run

    t = np.arange(0.0, 30.0, 0.1)
    ref = np.stack([1.5 * np.cos(t / 3), np.sin(t / 2), 0.1 * np.sin(t)], axis=1)
    run = tmp_path / "run"
    run.mkdir()
    _write_tum(tmp_path / "ref.tum", t, ref)
    _write_tum(run / "trajectory.tum", t, ref + [0.2, -0.1, 0.0])  # right scale
    _write_tum(run / "trajectory_loop_closed.tum", t, 1.01 * ref)
    acc = evaluate_run(tmp_path / "ref.tum", run)
    assert abs(acc["scale_error_loop_closed_pct"] - 100 * (1 - 1 / 1.01)) < 1e-3
    assert acc["scale_error_pct"] < 1e-3
    assert acc["ate_loop_closed_m"] > 0.004  # se3 keeps it
    assert acc["ate_se3_m"] < 1e-5


def test_loop_closed_scale_error_is_absent_without_a_loop_closed_trajectory(tmp_path) -> None:
    from tools.batch.measure import evaluate_run, scale_error_pct

    t = np.arange(0.0, 10.0, 0.1)
    ref = np.stack([np.cos(t), np.sin(t), 0.1 * t], axis=1)
    run = tmp_path / "run"
    run.mkdir()
    _write_tum(tmp_path / "ref.tum", t, ref)
    _write_tum(run / "trajectory.tum", t, ref)
    assert "scale_error_loop_closed_pct" not in evaluate_run(tmp_path / "ref.tum", run)
    _write_tum(run / "line.tum", t, np.stack([t, 0 * t, 0 * t], axis=1))  # collinear: no fit
    assert scale_error_pct(tmp_path / "ref.tum", run / "line.tum") is None

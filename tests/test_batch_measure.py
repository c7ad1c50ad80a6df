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

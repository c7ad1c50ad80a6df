"""The live pose's bound (``tools.live_bound``): the oracle joins the live pose before the first
loop closure to the loop-closed one after it, and its ATE says whether a live/loop-closed ratio
is within reach."""

from __future__ import annotations

import json

import numpy as np

from tools.live_bound import ORACLE_FILE, first_loop_closure_ns, live_bound, main


def _write_tum(path, t_s, xyz) -> None:
    rows = [f"{t:.3f} {x:.6f} {y:.6f} {z:.6f} 0 0 0 1" for t, (x, y, z) in zip(t_s, xyz)]
    path.write_text("# t x y z qx qy qz qw\n" + "\n".join(rows) + "\n")


def _run(tmp_path, loop_s: float | None):
    """A 30 s run: the live pose drifts 1 mm/s along x all along (odometry); the loop-closed one
    is within 0.5 mm everywhere."""
    t = np.arange(0.0, 30.0, 0.05)
    ref = np.stack([np.cos(t / 4), np.sin(t / 3), 0.05 * t], axis=1)
    rng = np.random.default_rng(3)
    drift = 1e-3 * t
    live = ref + np.stack([drift, 0 * t, 0 * t], axis=1) + rng.normal(0, 2e-4, ref.shape)
    lc = ref + rng.normal(0, 5e-4, ref.shape)
    run = tmp_path / "run"
    run.mkdir()
    _write_tum(tmp_path / "ref.tum", t, ref)
    _write_tum(run / "trajectory.tum", t, live)
    _write_tum(run / "trajectory_loop_closed.tum", t, lc)
    events = [{"t_ns": 0, "event": "map segment 0 started"}]
    if loop_s is not None:
        events += [
            {
                "t_ns": int((loop_s + 5) * 1e9),
                "event": "loop closed: keyframe 90 -> 3 (40 inliers)",
            },
            {"t_ns": int(loop_s * 1e9), "event": "loop closed: keyframe 60 -> 0 (50 inliers)"},
        ]
    (run / "stats.json").write_text(json.dumps({"events": events}))
    return tmp_path / "ref.tum", run


def test_the_oracle_is_live_before_the_first_loop_and_loop_closed_after(tmp_path) -> None:
    seq, run = _run(tmp_path, loop_s=20.0)
    b = live_bound(seq, run)
    assert b.first_loop_s == 20.0
    assert b.loop_closed_m < b.oracle_m < b.live_m
    assert b.live_after_loop_m is not None and b.live_after_loop_m > b.loop_closed_m
    # the oracle's samples: live's before 20 s, loop-closed's from 20 s on
    oracle = np.loadtxt(run / ORACLE_FILE)
    live = np.loadtxt(run / "trajectory.tum")
    lc = np.loadtxt(run / "trajectory_loop_closed.tum")
    np.testing.assert_array_equal(oracle[:, 0], live[:, 0])
    early = live[:, 0] < 20.0
    np.testing.assert_allclose(oracle[early], live[early])
    np.testing.assert_allclose(oracle[~early], lc[~early])
    # 20 s of drift up to 2 cm: no live pose can come within 1.5x of a 0.5 mm loop-closed one
    assert not b.reachable
    assert b.oracle_m > 5 * b.loop_closed_m


def test_an_early_loop_puts_the_bar_within_reach(tmp_path) -> None:
    seq, run = _run(tmp_path, loop_s=0.5)
    b = live_bound(seq, run, ratio=1.5)
    assert b.reachable
    assert b.oracle_m <= 1.5 * b.loop_closed_m


def test_a_run_without_loop_closure_is_its_own_bound(tmp_path, capsys) -> None:
    seq, run = _run(tmp_path, loop_s=None)
    assert first_loop_closure_ns(json.loads((run / "stats.json").read_text())) is None
    b = live_bound(seq, run)
    assert b.first_loop_s is None and b.live_after_loop_m is None
    assert b.oracle_m == b.live_m
    assert main([str(seq), str(run), "--out", str(tmp_path / "b.json")]) == 0
    assert "out of reach" in capsys.readouterr().out
    rows = json.loads((tmp_path / "b.json").read_text())
    assert rows[0]["reachable"] is False


def test_a_folder_that_is_not_a_run_is_a_one_line_error(tmp_path, capsys) -> None:
    seq, _ = _run(tmp_path, loop_s=20.0)
    (tmp_path / "empty").mkdir()
    assert main([str(seq), str(tmp_path / "empty")]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "no stats.json" in err

"""slam bench's suite variants: several renders of each sequence, realistic cameras, medians
over renders, and the ratios of a comparison (realistic over clean)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from tools.benchmark import (
    STANDARD_SUITE,
    bench_rows,
    bench_spec,
    ensure_sequence,
    markdown_table,
    suite_run_name,
    suite_variant,
)


def test_renders_differ_only_in_their_seed_and_keep_the_clean_cache_names() -> None:
    suite = suite_variant(STANDARD_SUITE, renders=3)
    assert len(suite) == 3 * len(STANDARD_SUITE)
    loop = [e for e in suite if e.name == "room-loop"]
    assert [e.seed for e in loop] == [2, 12, 22]
    assert {(e.profile, e.duration_s, e.scale, e.camera) for e in loop} == {
        ("loop", 80.0, "room", "clean")
    }
    # the clean suite's files keep their names (existing caches stay valid)
    assert loop[0].file_name() == "room-loop-loop-80s-seed2-v1.mcap"
    assert len({e.file_name() for e in suite}) == len(suite)
    real = suite_variant(STANDARD_SUITE, 20.0, "realistic")
    assert [e.seed for e in real] == [e.seed for e in STANDARD_SUITE]
    assert all(e.duration_s == 20.0 and "-realistic-" in e.file_name() for e in real)
    assert [suite_run_name(e, suite) for e in loop] == [
        "room-loop-seed2",
        "room-loop-seed12",
        "room-loop-seed22",
    ]
    assert suite_run_name(real[0], real) == "room-figure8"


def test_rows_are_medians_over_renders_and_repeats() -> None:
    def rec(seq: str, config: str, ate: float) -> dict:
        return {"sequence": seq, "config": config, "status": "ok", "metrics": {"ate_se3_m": ate}}

    records = [
        rec("hall-seed4", "default", 0.010),
        rec("hall-seed14", "default", 0.030),
        rec("hall-seed24", "default", 0.012),
        rec("hall-seed4", "loop-off", 0.040),
        rec("hall-seed14", "loop-off", 0.020),
        rec("hall-seed24", "loop-off", 0.050),
        {"sequence": "hall-seed24", "config": "default", "status": "failed", "metrics": {}},
    ]
    rows_of = {f"hall-seed{s}": "hall" for s in (4, 14, 24)}
    (row,) = bench_rows(records, "default", rows_of)
    assert row["sequence"] == "hall" and row["repeats"] == 3
    assert row["ate_se3_m"] == pytest.approx(0.012)
    assert row["ate_loop_off_m"] == pytest.approx(0.040)
    # without the mapping every render is its own row
    assert len(bench_rows(records, "default")) == 3


def test_comparison_shows_ate_ratios() -> None:
    new = [{"sequence": "hall", "ate_se3_m": 0.015, "completion_pct": 99.0}]
    old = {"hall": {"sequence": "hall", "ate_se3_m": 0.010, "completion_pct": 100.0}}
    table = markdown_table(new, old)
    assert "0.0150 (+0.0050, x1.50)" in table
    assert "99.0 (-1.0)" in table  # not an ATE: no ratio


def test_realistic_suite_render_has_blur_and_the_same_trajectory(tmp_path: Path) -> None:
    from datasets.open import open_sequence

    (clean,) = [e for e in suite_variant(STANDARD_SUITE, 2.5) if e.name == "room-aggressive"]
    (real,) = [e for e in suite_variant(STANDARD_SUITE, 2.5, "realistic") if e.name == clean.name]
    a = open_sequence(ensure_sequence(clean, tmp_path, progress=False))
    b = open_sequence(ensure_sequence(real, tmp_path, progress=False))
    assert a.ground_truth is not None and b.ground_truth is not None
    # the same trajectory (the realistic file also has poses at mid-exposure stamps)
    ta, tb = a.ground_truth.t_ns, b.ground_truth.t_ns
    common = np.intersect1d(ta, tb)
    assert len(common) >= 0.9 * len(ta)
    pa = a.ground_truth.positions_m[np.searchsorted(ta, common)]
    pb = b.ground_truth.positions_m[np.searchsorted(tb, common)]
    assert np.abs(pa - pb).max() < 1e-9
    # the effects are on: realistic frames have exposures (blur windows), clean ones none
    assert a.exposures_ns() is None
    exposures = b.exposures_ns()
    assert exposures is not None and (np.asarray(exposures) > 0).all()


def test_bench_spec_names_every_render(tmp_path: Path) -> None:
    suite = suite_variant(STANDARD_SUITE, 0.5, renders=2)[:2]
    spec = bench_spec([], suite, tmp_path, sequential=True)
    assert [s.name for s in spec.sequences] == ["room-figure8-seed1", "room-figure8-seed11"]
    assert spec.sequential


def test_bench_refuses_an_unknown_suite_sequence_or_zero_renders(tmp_path: Path, capsys) -> None:
    from tools.cli import main as slam

    out = tmp_path / "b"
    assert slam(["bench", "--out", str(out), "--only", "room-loop,corridor"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err == [
        "slam bench: error: --only: no suite sequence corridor (known: room-figure8, room-loop, "
        "room-aggressive, hall)"
    ]
    assert slam(["bench", "--out", str(out), "--renders", "0"]) == 2
    assert "--renders and --repeats must be at least 1" in capsys.readouterr().err
    assert not out.exists()

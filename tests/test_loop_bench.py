"""slam bench's loop-closure baseline: the loop-off config and the table columns."""

from __future__ import annotations

from pathlib import Path

import yaml

from slam.config import config_to_yaml, load_config, preset_config
from tools.benchmark import STANDARD_SUITE, loop_off_config, markdown_table, quick_suite


def test_loop_off_config_keeps_everything_else(tmp_path: Path) -> None:
    cfg = preset_config("euroc-stereo-imu")
    cfg.loop.min_inliers = 41
    run = tmp_path / "run"
    run.mkdir()
    (run / "config.yaml").write_text(config_to_yaml(cfg))
    dest = loop_off_config(run, tmp_path / "off" / "cfg.yaml")
    assert dest is not None
    off = load_config(str(dest))
    assert off.loop_closure is False
    assert off.use_imu is True and off.loop.min_inliers == 41
    on = yaml.safe_load((run / "config.yaml").read_text())
    on["loop_closure"] = False
    assert yaml.safe_load(dest.read_text()) == on


def test_no_baseline_when_loop_closure_was_off(tmp_path: Path) -> None:
    (tmp_path / "config.yaml").write_text(config_to_yaml(preset_config("stereo-vo")))
    assert loop_off_config(tmp_path, tmp_path / "x.yaml") is None


def test_table_has_loop_columns_and_suite_flags() -> None:
    row = {"sequence": "hall", "ate_loop_closed_m": 0.014, "ate_loop_off_m": 0.034}
    row["loop_ratio"] = row["ate_loop_closed_m"] / row["ate_loop_off_m"]
    table = markdown_table([row])
    assert "ATE loop off (m)" in table and "closed/off" in table
    assert "| 0.0340 | 0.41 |" in table
    assert all(e.revisits for e in STANDARD_SUITE)
    assert all(e.revisits for e in quick_suite(10.0))

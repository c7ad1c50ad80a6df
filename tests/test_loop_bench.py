"""slam bench's loop-closure baseline: the loop-off configuration and the table columns."""

from __future__ import annotations

from pathlib import Path

import yaml

from slam.config import config_to_yaml, load_config, preset_config
from tools.benchmark import STANDARD_SUITE, loop_off_choice, markdown_table, quick_suite


def test_loop_off_config_keeps_everything_else(tmp_path: Path) -> None:
    from tools.batch.spec import ConfigChoice, resolve_config

    cfg = preset_config("euroc-stereo-imu")
    cfg.loop.min_inliers = 41
    base_file = tmp_path / "base.yaml"
    base_file.write_text(config_to_yaml(cfg))
    choice = loop_off_choice(ConfigChoice("base", str(base_file)), "euroc-stereo-imu")
    assert choice is not None
    _, text = resolve_config(choice)
    assert text is not None
    dest = tmp_path / "off.yaml"
    dest.write_text(text)
    off = load_config(str(dest))
    assert off.loop_closure is False
    assert off.use_imu is True and off.loop.min_inliers == 41
    on = yaml.safe_load(base_file.read_text())
    on["loop_closure"] = False
    assert yaml.safe_load(text) == on
    # slam run's own default (the sequence has an IMU): its loop closure turned off, only that
    _, text = resolve_config(loop_off_choice(ConfigChoice("default"), "euroc-stereo-imu"))
    assert yaml.safe_load(text) == {"loop_closure": False}


def test_no_baseline_when_loop_closure_was_off(tmp_path: Path) -> None:
    from tools.batch.spec import ConfigChoice

    (tmp_path / "vo.yaml").write_text(config_to_yaml(preset_config("stereo-vo")))
    assert loop_off_choice(ConfigChoice("vo", str(tmp_path / "vo.yaml")), "stereo-vo") is None
    assert loop_off_choice(ConfigChoice("stereo-vo", "stereo-vo"), "euroc-stereo-imu") is None


def test_table_has_loop_columns_and_suite_flags() -> None:
    row = {"sequence": "hall", "ate_loop_closed_m": 0.014, "ate_loop_off_m": 0.034}
    row["loop_ratio"] = row["ate_loop_closed_m"] / row["ate_loop_off_m"]
    table = markdown_table([row])
    assert "ATE loop off (m)" in table and "closed/off" in table
    assert "| 0.0340 | 0.41 |" in table
    assert all(e.revisits for e in STANDARD_SUITE)
    assert all(e.revisits for e in quick_suite(10.0))

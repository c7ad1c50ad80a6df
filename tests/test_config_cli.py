"""`slam config show` lists every key with its value, unit, range and doc; a misspelt key gets
a suggestion; `slam run --help` says what SEQ is and where the keys are listed."""

from __future__ import annotations

import dataclasses
import os
import subprocess
import sys
import typing
from pathlib import Path

import pytest
from conftest import PROJECT_ROOT

from slam.config import SlamConfig, load_config
from slam.core.bounds import UNIT_KEY, field_unit, name_unit
from slam.core.errors import SlamError
from tools.cli import main as slam
from tools.cmd_config import describe


def _leaf_fields(cls: type, where: str = "") -> list[tuple[str, dataclasses.Field]]:
    hints = typing.get_type_hints(cls)
    out = []
    for f in dataclasses.fields(cls):
        if dataclasses.is_dataclass(hints[f.name]):
            out += _leaf_fields(hints[f.name], f"{where}{f.name}.")
        else:
            out.append((f"{where}{f.name}", f))
    return out


def test_show_prints_value_unit_range_and_doc(capsys) -> None:
    assert slam(["config", "show"]) == 0
    lines = capsys.readouterr().out.splitlines()
    i = lines.index("frontend.max_features = 220    in [1, 5000]")
    assert lines[i + 1] == "    Target number of tracked features (grid-bucketed)."
    assert "frontend.min_depth_m = 0.2 m    in (0, inf), less than frontend.max_depth_m" in lines
    assert "backend.moving_init_max_gravity_error = 0.5 m/s^2    in (0, inf)" in lines
    assert "backend.init_mode = auto" in lines
    assert "use_imu = false" in lines
    assert "backend: Every tunable of the back end." in lines
    assert max(len(line) for line in lines) <= 100


def test_show_a_preset_and_a_file(tmp_path: Path, capsys) -> None:
    assert slam(["config", "show", "euroc-stereo-imu"]) == 0
    out = capsys.readouterr().out
    assert out.startswith("Every configuration key of preset euroc-stereo-imu:")
    assert "\nuse_imu = true\n" in out and "\nloop_closure = true\n" in out
    cfg = tmp_path / "c.yaml"
    cfg.write_text("preset: euroc-stereo-imu\nfrontend:\n  max_features: 300\n")
    assert slam(["config", "show", str(cfg)]) == 0
    out = capsys.readouterr().out
    assert " ".join(out.split()).startswith(f"Every configuration key of {cfg} (euroc-stereo-imu):")
    assert "\nfrontend.max_features = 300    in [1, 5000]\n" in out


def test_show_an_unknown_preset_is_one_line(capsys) -> None:
    assert slam(["config", "show", "stereo-imu"]) == 2
    err = capsys.readouterr().err
    assert err == (
        "slam config: error: config 'stereo-imu' is neither a preset "
        "(euroc-mono-imu, euroc-stereo-imu, stereo-vo) nor a YAML file\n"
    )


def test_every_key_once_with_a_doc() -> None:
    keys = describe(SlamConfig())
    assert [k.key for k in keys] == [key for key, _ in _leaf_fields(SlamConfig)]
    undocumented = [k.key for k in keys if not k.doc]
    assert not undocumented, f"fields without a docstring: {undocumented}"


@pytest.mark.parametrize("key, f", _leaf_fields(SlamConfig), ids=lambda v: str(v)[:40])
def test_a_unit_has_one_home(key: str, f: dataclasses.Field) -> None:
    """A unit in the name (``_m``, ``_px``) or in ``bounded(unit=...)``, never both."""
    assert not (f.metadata.get(UNIT_KEY) and name_unit(f.name)), key


def test_units_from_names() -> None:
    assert name_unit("odom_sigma_m_per_sqrt_s") == "m/sqrt(s)"
    assert name_unit("max_accel_m_s2") == "m/s^2"
    assert name_unit("still_gyro_std_rad_s") == "rad/s"
    assert name_unit("gil_switch_interval_ms") == "ms"
    assert name_unit("odom_sigma_rad_ratio") == ""
    units = {key: field_unit(f) for key, f in _leaf_fields(SlamConfig)}
    assert units["loop.gate_deg_per_m"] == "deg/m"
    assert units["backend.moving_init_max_gravity_error"] == "m/s^2"


@pytest.mark.parametrize(
    "yaml_text, message",
    [
        (
            "frontend:\n  max_featurs: 300\n",
            "unknown config key frontend.max_featurs (did you mean `frontend.max_features`?); "
            "valid keys of frontend: ",
        ),
        (
            "max_features: 300\n",
            "unknown config key max_features (did you mean `frontend.max_features`?); valid keys: ",
        ),
        (
            "min_depth_m: 3\n",
            "unknown config key min_depth_m (did you mean `frontend.min_depth_m` or "
            "`backend.min_depth_m`?); valid keys: ",
        ),
        ("frontend:\n  zzz: 3\n", "unknown config key frontend.zzz; valid keys of frontend: "),
    ],
)
def test_a_misspelt_key_gets_a_suggestion(tmp_path: Path, yaml_text: str, message: str) -> None:
    path = tmp_path / "c.yaml"
    path.write_text(yaml_text)
    with pytest.raises(SlamError) as err:
        load_config(str(path))
    text = str(err.value)
    assert text.startswith(message), text
    assert text.endswith(" (every key: slam config show)")
    assert "\n" not in text


def test_a_closed_pipe_ends_quietly() -> None:
    """`slam config show | head -1`: no traceback when the reader has gone."""
    read_end, write_end = os.pipe()
    os.close(read_end)
    try:
        proc = subprocess.run(
            [sys.executable, "-m", "tools.cli", "config", "show"],
            stdout=write_end,
            stderr=subprocess.PIPE,
            text=True,
            cwd=PROJECT_ROOT,
        )
    finally:
        os.close(write_end)
    assert proc.returncode == 141
    assert proc.stderr == ""

"""Every numeric config field has bounds; out-of-range configs are one-line errors before a run."""

from __future__ import annotations

import dataclasses
import math
import subprocess
import sys
import typing
from pathlib import Path
from typing import Any

import pytest
from conftest import PROJECT_ROOT

from slam.config import (
    PRESETS,
    SlamConfig,
    config_to_yaml,
    load_config,
    preset_config,
    validate_config,
)
from slam.core.bounds import Bounds, field_bounds
from slam.core.errors import SlamError


def _numeric(hint: Any) -> bool:
    """int or float, possibly inside ``X | None`` (bool is not numeric here)."""
    args = typing.get_args(hint) or (hint,)
    return any(a in (int, float) for a in args)


def _walk(cls: type, where: str = "") -> list[tuple[str, type, dataclasses.Field[Any], Any]]:
    """(key path, owning class, field, field type) of every field reachable from ``cls``."""
    hints = typing.get_type_hints(cls)
    out = []
    for f in dataclasses.fields(cls):
        hint = hints[f.name]
        key = f"{where}{f.name}"
        if isinstance(hint, type) and dataclasses.is_dataclass(hint):
            out.extend(_walk(hint, f"{key}."))
        else:
            out.append((key, cls, f, hint))
    return out


NUMERIC = [(key, cls, f, hint) for key, cls, f, hint in _walk(SlamConfig) if _numeric(hint)]


def test_the_walk_reaches_every_nested_config() -> None:
    sections = {key.split(".")[0] for key, *_ in NUMERIC}
    assert sections == {"frontend", "backend", "loop", "mapping", "player", "viz"}
    assert len(NUMERIC) >= 100


@pytest.mark.parametrize("key, cls, f, hint", NUMERIC, ids=[n[0] for n in NUMERIC])
def test_every_numeric_field_has_bounds_around_its_default(
    key: str, cls: type, f: dataclasses.Field[Any], hint: Any
) -> None:
    """A new numeric field without ``bounded(...)`` fails here."""
    bounds = field_bounds(f)
    assert isinstance(bounds, Bounds), f"{key}: declare it with slam.core.bounds.bounded(...)"
    assert bounds.lo is not None and math.isfinite(bounds.lo)
    assert bounds.hi is None or (math.isfinite(bounds.hi) and bounds.hi > bounds.lo)
    default = f.default
    assert default is not dataclasses.MISSING, key
    assert type(default) is (int if hint is int else float), f"{key}: default {default!r}"
    assert bounds.contains(default), f"{key}: default {default!r} outside {bounds.interval()}"
    if bounds.below:
        other = {g.name: g for g in dataclasses.fields(cls)}[bounds.below]
        assert _numeric(typing.get_type_hints(cls)[other.name]), key
        assert default < other.default or (bounds.below_or_equal and default == other.default)


@pytest.mark.parametrize("name", sorted(PRESETS))
def test_presets_defaults_and_saved_configs_are_valid(name: str, tmp_path: Path) -> None:
    validate_config(SlamConfig())
    cfg = preset_config(name)
    saved = tmp_path / "config.yaml"
    saved.write_text(config_to_yaml(cfg))
    assert load_config(str(saved)) == cfg


def _outside(bounds: Bounds, is_int: bool) -> list[float]:
    """Values just outside ``bounds`` (for an int field, the nearest integers)."""
    step = 1 if is_int else 1e-3
    values = [bounds.lo if bounds.lo_open else bounds.lo - step]
    if bounds.hi is not None:
        values.append(bounds.hi if bounds.hi_open else bounds.hi + step)
    return [int(v) if is_int else float(v) for v in values]


def _replaced(cfg: Any, path: list[str], value: Any) -> Any:
    if len(path) == 1:
        return dataclasses.replace(cfg, **{path[0]: value})
    return dataclasses.replace(cfg, **{path[0]: _replaced(getattr(cfg, path[0]), path[1:], value)})


@pytest.mark.parametrize("key, cls, f, hint", NUMERIC, ids=[n[0] for n in NUMERIC])
def test_every_bound_is_enforced(key: str, cls: type, f: dataclasses.Field[Any], hint: Any) -> None:
    bounds = field_bounds(f)
    assert bounds is not None
    for value in _outside(bounds, hint is int):
        with pytest.raises(SlamError) as err:
            validate_config(_replaced(SlamConfig(), key.split("."), value))
        assert str(err.value).startswith(f"config key {key} must be in {bounds.interval()}, got")
    for bad in (math.nan, math.inf) if hint is float else (2.5, True):
        with pytest.raises(SlamError, match=f"config key {key} must be"):
            validate_config(_replaced(SlamConfig(), key.split("."), bad))


def _load_error(tmp_path: Path, text: str) -> str:
    path = tmp_path / "bad.yaml"
    path.write_text(text)
    with pytest.raises(SlamError) as err:
        load_config(str(path))
    message = str(err.value)
    assert "\n" not in message
    return message


@pytest.mark.parametrize(
    "text, message",
    [
        (
            "frontend:\n  max_features: -5\n",
            "config key frontend.max_features must be in [1, 5000], got -5",
        ),
        (
            "preset: euroc-stereo-imu\nbackend:\n  lag_s: .nan\n",
            "config key backend.lag_s must be a finite number in (0, inf), got nan",
        ),
        (
            "loop:\n  gate_ratio: .inf\n",
            "config key loop.gate_ratio must be a finite number in [0, inf), got inf",
        ),
        (
            "frontend:\n  klt_pyramid_levels: 2.5\n",
            "config key frontend.klt_pyramid_levels must be an integer in [0, inf), got 2.5",
        ),
        (
            "player:\n  max_frames: 10.0\n",
            "config key player.max_frames must be an integer in [0, inf), got 10.0",
        ),
        (
            "viz:\n  jpeg_quality: true\n",
            "config key viz.jpeg_quality must be a number in [0, 100], got True",
        ),
        (
            "mapping:\n  depth_scale: 0\n",
            "config key mapping.depth_scale must be in (0, 1], got 0.0",
        ),
        (
            "loop:\n  min_inlier_ratio: 1.5\n",
            "config key loop.min_inlier_ratio must be in [0, 1], got 1.5",
        ),
        (
            "frontend:\n  min_depth_m: 30\n  max_depth_m: 20\n",
            "config key frontend.min_depth_m must be less than frontend.max_depth_m (20.0), "
            "got 30.0",
        ),
        (
            "backend:\n  min_depth_m: 5\n  max_depth_m: 5\n",
            "config key backend.min_depth_m must be less than backend.max_depth_m (5.0), got 5.0",
        ),
        (
            "frontend:\n  keyframe_min_interval_s: 1\n",
            "config key frontend.keyframe_min_interval_s must be at most "
            "frontend.keyframe_max_interval_s (0.5), got 1.0",
        ),
        (
            "frontend:\n  max_features: 10\n",
            "config key frontend.min_pnp_inliers must be at most frontend.max_features (10), "
            "got 15",
        ),
        (
            "loop:\n  covisibility_edges: bogus\n",
            "config key loop.covisibility_edges must be one of off, found, tracked, got 'bogus'",
        ),
        (
            "loop:\n  live_correction: latests\n",
            "config key loop.live_correction must be one of unanchored, latest, got 'latests'",
        ),
        (
            "frontend:\n  affine_iterations: 0\n",
            "config key frontend.affine_iterations must be in [1, inf), got 0 "
            "(switch refinement off with frontend.affine_refinement: false)",
        ),
    ],
)
def test_out_of_range_yaml_is_a_one_line_error(tmp_path: Path, text: str, message: str) -> None:
    assert _load_error(tmp_path, text) == message


def test_a_min_equal_to_its_max_is_fine_where_the_range_is_inclusive(tmp_path: Path) -> None:
    path = tmp_path / "ok.yaml"
    path.write_text("frontend:\n  keyframe_min_interval_s: 0.5\n  keyframe_max_interval_s: 0.5\n")
    assert load_config(str(path)).frontend.keyframe_min_interval_s == 0.5


def test_config_imports_no_stage() -> None:
    """slam.config (and every config module it nests) stays light: no stage, worker or OpenCV."""
    code = (
        "import sys, slam.config\n"
        "print(' '.join(m for m in sys.modules if m.endswith('stage') or m.startswith('slam.runtime') or m in "
        "('slam.worker', 'cv2', 'gtsam', 'numpy')))\n"
    )
    proc = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, cwd=PROJECT_ROOT, check=True
    )
    assert proc.stdout.strip() == ""


@pytest.fixture(scope="module")
def tiny_seq(tmp_path_factory: pytest.TempPathFactory) -> Path:
    from datasets.mcap_io import write_sequence_mcap
    from datasets.memory import random_sequence

    path = tmp_path_factory.mktemp("seq") / "tiny.mcap"
    write_sequence_mcap(random_sequence(num_frames=3, seed=1), path, progress=False)
    return path


def test_slam_run_with_a_bad_config_fails_in_one_line_before_the_run(
    tiny_seq: Path, tmp_path: Path
) -> None:
    bad = tmp_path / "bad.yaml"
    bad.write_text("frontend:\n  max_features: -5\n")
    out = tmp_path / "run"
    proc = subprocess.run(
        [sys.executable, "-m", "tools.cli", "run", str(tiny_seq), "--out", str(out)]
        + ["--config", str(bad), "--no-progress"],
        capture_output=True,
        text=True,
        cwd=PROJECT_ROOT,
        timeout=120,
    )
    assert proc.returncode == 2
    assert proc.stderr.strip().splitlines() == [
        "slam run: error: config key frontend.max_features must be in [1, 5000], got -5"
    ]
    assert "Traceback" not in proc.stderr and proc.stdout == ""
    assert not out.exists()  # nothing ran, nothing written


def test_cli_overrides_are_checked_before_the_run(tiny_seq: Path, tmp_path: Path, capsys) -> None:
    """``--max-frames`` changes the loaded config; it is checked again before the run."""
    from tools.cli import main as slam

    out = tmp_path / "run"
    argv = ["run", str(tiny_seq), "--out", str(out), "--max-frames", "-3", "--no-progress"]
    assert slam(argv) == 2
    assert capsys.readouterr().err.strip().splitlines() == [
        "slam run: error: config key player.max_frames must be in [0, inf), got -3"
    ]
    assert not out.exists()  # checked before the output folder is made


def test_run_slam_checks_the_config_it_is_given(tmp_path: Path) -> None:
    """Programmatic runs (benchmarks, tools) get the same check before anything starts."""
    from datasets.memory import random_sequence
    from slam.runtime.wiring import run_slam

    cfg = preset_config("stereo-vo")
    cfg.frontend.max_features = -5
    with pytest.raises(SlamError, match=r"frontend.max_features must be in \[1, 5000\], got -5"):
        run_slam(random_sequence(num_frames=3), cfg, tmp_path / "run", progress=False)
    assert not (tmp_path / "run").exists()

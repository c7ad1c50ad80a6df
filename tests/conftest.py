"""Shared fixtures: where the shared real data lives (skip with a reason when absent)."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

PROJECT_ROOT = Path(__file__).resolve().parents[1]


def data_dir() -> Path:
    return Path(os.environ.get("SLAM_DATA_DIR", PROJECT_ROOT.parent / "shared" / "data"))


@pytest.fixture(scope="session")
def shared_data() -> Path:
    d = data_dir()
    if not d.is_dir():
        pytest.skip(f"shared data not found at {d} (set SLAM_DATA_DIR)")
    return d


def require(path: Path) -> Path:
    """Skip the calling test when a shared-data file or folder is missing."""
    if not path.exists():
        pytest.skip(f"shared data missing: {path}")
    return path


def in_memory(seq):  # type: ignore[no-untyped-def]
    """Render every frame of a sequence once, so repeated runs do not pay for rendering."""
    from datasets.memory import InMemorySequence

    frames = list(seq.iter_frames())
    return InMemorySequence(
        seq.name,
        seq.calibration,
        seq.frame_times_ns(),
        [f.left for f in frames],
        [f.right for f in frames],
        seq.imu(),
        seq.ground_truth,
    )


def synth_mcap(path: Path, profile: str, duration_s: float) -> Path:
    """A synthetic sequence written by `slam synth` (in this process)."""
    from tools.cli import main as slam

    assert (
        slam(["synth", str(path), "--profile", profile, "--duration", str(duration_s), "-q"]) == 0
    )
    return path

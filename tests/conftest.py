"""Shared fixtures: where the shared real data lives (skip with a reason when absent)."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest

from slam.core.messages import TrackingResult

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


def tracking_result(
    t_ns: int,
    world_from_body: np.ndarray | None,
    *,
    frame_index: int | None = None,
    segment: int = 0,
    anchor: int = -1,
    time_offset_ns: int = 0,
) -> TrackingResult:
    """A front-end result with no features, for tests of what consumes poses (recorder,
    viewer, live pose): tracking when there is a pose, lost without."""
    return TrackingResult(
        t_ns=t_ns,
        frame_index=t_ns if frame_index is None else frame_index,
        state="tracking" if world_from_body is not None else "lost",
        segment_id=segment,
        world_from_body=world_from_body,
        is_keyframe=False,
        keyframe_id=-1,
        num_tracked=0,
        num_inliers=0,
        feature_pixels=np.zeros((0, 2)),
        feature_ages=np.zeros(0),
        latency_ms=1.0,
        anchor_keyframe_id=anchor,
        time_offset_ns=time_offset_ns,
    )

"""Shared fixtures: where the shared real data lives (skip with a reason when absent)."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest

from slam.core.messages import Keyframe, TrackingResult

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


@pytest.fixture(scope="module")
def euroc_micro_imu_gt(shared_data: Path) -> tuple[np.ndarray, np.ndarray]:
    """The real V1_01 IMU (EuRoC csv rows: t_ns, gyro rad/s, accel m/s^2) and the recomputed
    OpenVINS ground truth (20 Hz, EuRoC columns: t_ns, p, q_wxyz, v, b_gyro, b_accel); the
    200 Hz state_groundtruth_estimate0/data.csv is not part of the shared snapshot."""
    root = shared_data / "euroc_v101_micro"
    imu = np.loadtxt(require(root / "mav0/imu0/data.csv"), delimiter=",", comments="#")
    gt = np.loadtxt(
        require(root / "groundtruth_openvins/V1_01_easy.csv"), delimiter=",", comments="#"
    )
    return imu, gt


def pose_keyframe(
    t_ns: int, keyframe_id: int, world_from_body: np.ndarray, previous: np.ndarray | None = None
) -> Keyframe:
    """A keyframe with a pose and no features, for tests of the back end's IMU side;
    ``previous``: the previous keyframe's pose (id ``keyframe_id - 1``), none for the first."""
    return Keyframe(
        t_ns=t_ns,
        keyframe_id=keyframe_id,
        frame_index=keyframe_id,
        segment_id=0,
        world_from_body_vo=world_from_body,
        landmark_ids=np.zeros(0, np.int64),
        pixels_left_undist=np.zeros((0, 2)),
        pixels_right_undist=np.zeros((0, 2)),
        points_world_vo=np.zeros((0, 3)),
        image_left=np.zeros((0, 0), np.uint8),
        image_right=None,
        previous_keyframe_id=keyframe_id - 1 if previous is not None else -1,
        previous_keyframe_world_from_body=previous,
    )


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

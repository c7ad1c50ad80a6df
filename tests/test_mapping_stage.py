"""The live mapper stage: lag and drops are reported in its stats (stats.json 'mapping')."""

from __future__ import annotations

import os

import numpy as np
import pytest
from synthetic_planes import PlaneScene, orbit_poses

from mapping.config import MapperStageConfig
from slam.core.calibration import Calibration, CameraCalibration, CameraIntrinsics, ImuCalibration
from slam.core.messages import Keyframe
from slam.runtime.mapper import MapperStage

W, H = 320, 240
K = np.array([[230.0, 0.0, 160.0], [0.0, 230.0, 120.0], [0.0, 0.0, 1.0]])


def _calibration() -> Calibration:
    intr = CameraIntrinsics(W, H, 230.0, 230.0, 160.0, 120.0)
    right = np.eye(4)
    right[0, 3] = 0.11  # body_from_cam1: 11 cm to the right
    cams = (CameraCalibration("cam0", intr), CameraCalibration("cam1", intr, right))
    return Calibration(cams, ImuCalibration(), 0)


def _keyframes(n: int) -> list[Keyframe]:
    scene = PlaneScene()
    out = []
    for i, pose in enumerate(orbit_poses(n)):
        left, _ = scene.render(pose, K, (H, W))
        right_pose = pose.copy()
        right_pose[:3, 3] += pose[:3, 0] * 0.11
        right, _ = scene.render(right_pose, K, (H, W))
        empty = np.zeros((0, 2))
        out.append(
            Keyframe(
                int(i * 0.5e9),
                i,
                i,
                0,
                pose,
                np.zeros(0, np.int64),
                empty,
                empty,
                np.zeros((0, 3)),
                left,
                right,
            )  # fmt: skip
        )
    return out


@pytest.mark.parametrize("threaded", [False, True])
def test_stage_reports_lag_and_drops(threaded):
    cfg = MapperStageConfig(enabled=True, num_planes=32, max_backlog=1, final_reintegration=False)
    stage = MapperStage(_calibration(), cfg, threaded=threaded)
    kfs = _keyframes(6)
    for kf in kfs:  # a burst: the worker cannot finish one before the next arrives
        stage.process(kf)
    stage.finish({}, None)
    stats = stage.stats()
    assert stats["keyframes_received"] == len(kfs)
    # dropped keyframes with a new view are sent at the end (caught up)
    sent_live = stats["keyframes_sent"] - stats["keyframes_caught_up"]
    assert sent_live + stats["keyframes_dropped_lag"] == len(kfs)
    processed = stats["keyframes_fused"] + stats["keyframes_skipped_static"]
    assert processed == stats["keyframes_sent"]
    assert stats["lag_wall_s"]["count"] == processed
    assert stats["lag_behind_s"]["count"] == processed
    assert stats["lag_wall_s"]["p50_s"] > 0
    assert stats["keeps_up"] == (stats["keyframes_dropped_lag"] == 0)
    if threaded:  # the burst overflows a backlog of one keyframe
        assert stats["keyframes_dropped_lag"] >= 1 and not stats["keeps_up"]
        # The worker process's CPU per fused keyframe (depth + fusion take some).
        assert stats["cpu_per_keyframe"]["count"] == stats["keyframes_fused"]
        assert stats["cpu_per_keyframe"]["p50_ms"] > 0
        assert stats["dropped_fraction"] == stats["keyframes_dropped_lag"] / len(kfs)
    else:  # in-process: every keyframe is mapped before the next, never behind
        assert stats["keyframes_dropped_lag"] == 0
        assert stats["lag_behind_s"]["max_s"] == 0.0
        assert stats["cpu_per_keyframe"] is None  # the process's CPU is not the mapper's alone


def test_loop_correction_moves_the_map_during_the_run():
    """In-process stage: keyframes fused, a loop correction shifts the map by 5 cm; the
    keyframes it moved are re-integrated a few per new keyframe, and keyframes after it arrive
    in the corrected map frame."""
    from slam.core.messages import LoopCorrection

    cfg = MapperStageConfig(
        enabled=True, num_planes=16, reintegrate_per_keyframe=2, final_reintegration=False
    )
    stage = MapperStage(_calibration(), cfg, threaded=False)
    kfs = _keyframes(8)
    for kf in kfs[:4]:
        stage.process(kf)
    shift = np.eye(4)
    shift[:3, 3] = [0.05, 0.0, 0.0]
    corrected = {kf.keyframe_id: shift @ kf.world_from_body_vo for kf in kfs[:4]}
    stage.process(LoopCorrection(kfs[3].t_ns, 0, 3, 0, 50, 1, {0: shift}, corrected))
    for kf in kfs[4:]:
        stage.process(kf)
    mapper = stage._core.mapper  # in-process: the core lives here
    stats = stage.stats()
    fused_before = [kf.t_ns for kf in kfs[:4] if kf.t_ns in mapper._keyframes]
    assert stats["loop_corrections_received"] == 1
    assert stats["loop_reintegrated"] == len(fused_before) >= 3
    for kf in kfs:
        stored = mapper._keyframes.get(kf.t_ns)
        if stored is not None:  # every fused keyframe sits in the corrected map
            want = shift @ kf.world_from_body_vo
            np.testing.assert_allclose(stored.world_from_view[:3, 3], want[:3, 3], atol=1e-9)
    stage.finish({}, None)


def test_spread_order_is_a_permutation_spread_over_the_range():
    from slam.runtime.mapper import spread_order

    assert spread_order(0) == []
    assert spread_order(1) == [0]
    order = spread_order(10)
    assert sorted(order) == list(range(10))
    assert order[:4] == [0, 8, 4, 2]  # each prefix halves the largest gap


def test_dropped_new_views_are_fused_at_the_end():
    """A burst overflows a backlog of one keyframe; the dropped keyframes (all new views on the
    orbit) are held and fused at the end at their final poses: every keyframe ends up fused
    or skipped as static, none lost, while the live drop count stays what it was."""
    cfg = MapperStageConfig(enabled=True, num_planes=32, max_backlog=1, final_reintegration=True)
    stage = MapperStage(_calibration(), cfg, threaded=True)
    kfs = _keyframes(6)
    for kf in kfs:
        stage.process(kf)
    stage.finish({kf.t_ns: kf.world_from_body_vo for kf in kfs}, None)
    stats = stage.stats()
    assert stats["keyframes_dropped_lag"] >= 1
    assert stats["keyframes_caught_up"] == stats["keyframes_dropped_lag"]
    assert stats["keyframes_sent"] == len(kfs)
    assert stats["keyframes_fused"] + stats["keyframes_skipped_static"] == len(kfs)


def test_dropped_repeat_views_are_not_held():
    """A keyframe that repeats a view already sent (same pose) is dropped for good."""
    cfg = MapperStageConfig(enabled=True, num_planes=32, max_backlog=1, final_reintegration=False)
    stage = MapperStage(_calibration(), cfg, threaded=True)
    kf = _keyframes(1)[0]
    assert stage._is_new_view(kf.world_from_body_vo)
    stage._sent_poses.append(kf.world_from_body_vo)
    moved = kf.world_from_body_vo.copy()
    moved[:3, 3] += [0.05, 0.0, 0.0]  # 5 cm, same direction: not new
    assert not stage._is_new_view(moved)
    moved[:3, 3] += [0.10, 0.0, 0.0]  # 15 cm: new
    assert stage._is_new_view(moved)
    stage.finish(None, None)


def test_a_full_hold_is_thinned_and_stays_spread_over_the_run():
    """Hold of 4, 12 dropped keyframes 1 m apart on a line (all new views): the hold never
    exceeds 4 and ends as every 4th of them, from the start of the line to its end."""
    from slam.core.messages import MapKeyframe

    cfg = MapperStageConfig(enabled=True, num_planes=16, catch_up_max_keyframes=4)
    stage = MapperStage(_calibration(), cfg, threaded=False)
    img = np.zeros((H, W), np.uint8)
    for i in range(12):
        pose = np.eye(4)
        pose[0, 3] = float(i)
        assert stage._is_new_view(pose)
        stage._hold(MapKeyframe(i, img, img, pose))
        assert len(stage.held) <= 4
    xs = [h.world_from_cam0[0, 3] for h in stage.held]
    assert xs == [0.0, 4.0, 8.0]  # every 4th: an even subsample from the start
    stage.finish(None, None)


def _process_state(pid: int) -> str:
    from pathlib import Path

    return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]


def _wait_for(check, timeout_s: float) -> bool:
    import time

    deadline = time.monotonic() + timeout_s
    while not check() and time.monotonic() < deadline:
        time.sleep(0.01)
    return check()


@pytest.mark.skipif(not os.path.exists("/proc/self/stat"), reason="Linux /proc")
def test_front_end_frame_stops_a_working_mapper_and_resumes_it():
    """``paused_while_working`` (``mapping.pause_while_tracking``) stops the worker process for
    the frame only while it has a keyframe in hand, and the keyframe is fused once it resumes."""
    cfg = MapperStageConfig(enabled=True, num_planes=32, final_reintegration=False)
    stage = MapperStage(_calibration(), cfg, threaded=True, pausable=True)
    proc = stage._proc
    assert proc is not None and stage.pausable
    proc.wait_ready()
    pid = proc.pid
    assert pid is not None
    with stage.paused_while_working():  # nothing to work on: left alone
        assert _process_state(pid) != "T"
    assert stage.paused_frames == 0
    assert proc.pause()  # hold it so that the keyframe is still in hand below
    stage.process(_keyframes(1)[0])
    with stage.paused_while_working():
        assert _wait_for(lambda: _process_state(pid) == "T", 2.0)
        assert not _wait_for(lambda: len(stage.reports) > 0, 0.3)  # stopped: no work done
    assert _wait_for(lambda: _process_state(pid) != "T", 2.0)
    assert _wait_for(lambda: len(stage.reports) == 1, 60.0)  # resumed: fused
    assert stage.paused_frames == 1 and stage.stats()["paused_frames"] == 1
    stage.finish({}, None)
    assert stage.error is None

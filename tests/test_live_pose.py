"""The live pose is the best pose known when it is published: odometry composed with the
latest loop correction (trajectory.tum), the odometry kept apart (trajectory_odometry.tum),
each correction's jump measured and recorded."""

from __future__ import annotations

import dataclasses

import numpy as np
from conftest import synth_mcap, tracking_result

from datasets.rigs import euroc_like_calibration
from slam.config import FrontendConfig, preset_config
from slam.core.geometry import make_transform, so3_exp
from slam.core.messages import LoopCorrection
from slam.frontend.tracker import FrontEnd
from slam.runtime.frontend import FrontendStage


def _correction(generation: int, map_from_odom: dict[int, np.ndarray]) -> LoopCorrection:
    return LoopCorrection(0, generation, 1, 0, 50, generation, map_from_odom, {})


def test_published_pose_is_odometry_under_the_latest_correction() -> None:
    latest: list[LoopCorrection | None] = [None]
    fe = FrontEnd(euroc_like_calibration(), FrontendConfig())
    stage = FrontendStage(fe, threaded=False, queue_size=2, map_source=lambda: latest[0])
    odo = make_transform(so3_exp(np.array([0.0, 0.0, 0.3])), np.array([2.0, 1.0, 0.5]))
    first = stage._in_map(tracking_result(1, odo))
    np.testing.assert_array_equal(first.map_from_body, odo)  # no loop yet: the odometry
    assert first.map_generation == 0 and first.map_jump_m == 0.0
    fix = make_transform(so3_exp(np.array([0.0, 0.0, np.radians(2.0)])), np.array([0.1, 0, 0]))
    latest[0] = _correction(1, {0: fix})
    second = stage._in_map(tracking_result(2, odo))
    np.testing.assert_allclose(second.map_from_body, fix @ odo)
    np.testing.assert_array_equal(second.world_from_body, odo)  # the odometry never moves
    expected_m = float(np.linalg.norm((fix @ odo)[:3, 3] - odo[:3, 3]))
    assert second.map_generation == 1
    assert abs(second.map_jump_m - expected_m) < 1e-12 and abs(second.map_jump_deg - 2.0) < 1e-9
    third = stage._in_map(tracking_result(3, odo))  # the same correction: no new jump
    np.testing.assert_allclose(third.map_from_body, fix @ odo)
    assert third.map_jump_m == 0.0
    # tracked on old landmarks found again in the map: already in the map, published as is
    anchored = stage._in_map(tracking_result(3, odo, anchor=3))
    np.testing.assert_array_equal(anchored.map_from_body, odo)
    assert abs(anchored.map_jump_m - expected_m) < 1e-12  # leaving the correction is a jump
    other = stage._in_map(tracking_result(4, odo, segment=1))  # a segment it does not correct
    np.testing.assert_array_equal(other.map_from_body, odo)
    lost = stage._in_map(tracking_result(5, None))
    assert lost.map_from_body is None and lost.map_generation == 1


def test_latest_correction_also_moves_frames_on_old_landmarks() -> None:
    """``loop.live_correction: latest``: a frame tracked on old landmarks is published under
    the correction too; an unknown policy is refused."""
    import pytest

    from slam.core.errors import SlamError

    fix = make_transform(so3_exp(np.array([0.0, 0.0, np.radians(1.0)])), np.array([0, 0.05, 0]))
    fe = FrontEnd(euroc_like_calibration(), FrontendConfig())
    stage = FrontendStage(
        fe,
        threaded=False,
        queue_size=2,
        map_source=lambda: _correction(1, {0: fix}),
        live_correction="latest",
    )
    odo = make_transform(so3_exp(np.array([0.1, 0.0, 0.3])), np.array([2.0, 1.0, 0.5]))
    anchored = stage._in_map(tracking_result(1, odo, anchor=3))
    np.testing.assert_allclose(anchored.map_from_body, fix @ odo)
    with pytest.raises(SlamError, match="live_correction"):
        FrontendStage(fe, threaded=False, queue_size=2, live_correction="anchor")


def test_run_writes_live_and_odometry_trajectories(tmp_path) -> None:
    """A stereo-inertial run with loop closure: trajectory.tum is the odometry until the
    first correction and the corrected pose from then on; the first jump recorded in
    stats.json is the distance between the two at that frame."""
    import json

    from datasets.open import open_sequence
    from slam.runtime.wiring import run_slam

    seq = open_sequence(synth_mcap(tmp_path / "seq.mcap", "figure8", 36))
    cfg = dataclasses.replace(preset_config("euroc-stereo-imu"))
    # without map reuse, so that every frame after a loop is corrected (a frame tracked on
    # old landmarks is published as tracked)
    cfg.frontend.map_reuse = False
    cfg.player.sequential = True
    cfg.player.speed = 0.0
    res = run_slam(seq, cfg, tmp_path / "run", progress=False)
    live = np.loadtxt(tmp_path / "run" / "trajectory.tum")
    odo = np.loadtxt(tmp_path / "run" / "trajectory_odometry.tum")
    np.testing.assert_array_equal(live[:, 0], odo[:, 0])
    stats = json.loads((tmp_path / "run" / "stats.json").read_text())
    jumps = stats["live_map_corrections"]["jumps"]
    assert res.stats["loop_closure"]["accepted"] >= 1 and len(jumps) >= 1
    t0_s = jumps[0]["t_ns"] * 1e-9  # TUM times are the stamps in seconds
    first = int(np.argmin(np.abs(live[:, 0] - t0_s)))
    assert abs(live[first, 0] - t0_s) < 1e-6
    np.testing.assert_array_equal(live[:first, 1:4], odo[:first, 1:4])
    gap = np.linalg.norm(live[first, 1:4] - odo[first, 1:4])
    assert abs(gap - jumps[0]["metres"]) < 1e-6 and gap > 0

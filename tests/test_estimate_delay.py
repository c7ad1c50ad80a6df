"""A sequential run's back-end estimates delivered late (``player.sequential_estimate_delay_ms``):
each reaches the front end's slot once the IMU stream has passed its keyframe's stamp by the
delay, in order; the outputs downstream are not delayed; 0 publishes at once."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from datasets.memory import InMemorySequence
from datasets.rigs import euroc_like_calibration
from datasets.synth.vio_world import generate_world
from slam.backend.config import BackendConfig
from slam.backend.smoother import VioBackend
from slam.config import preset_config
from slam.core.errors import SlamError
from slam.core.geometry import make_transform
from slam.core.messages import BackendOutput, Estimate, ImuBatch, ImuSample, Keyframe
from slam.runtime.backend import BackendStage
from slam.runtime.stage import Latest
from slam.runtime.wiring import run_slam

MS = 1_000_000


def _stage(delay_ms: int) -> tuple[BackendStage, Latest, list[object]]:
    latest = Latest()
    stage = BackendStage(
        euroc_like_calibration(),
        BackendConfig(),
        latest,
        False,
        False,
        estimate_delay_ns=delay_ms * MS,
    )
    emitted: list[object] = []

    class _Sink:
        def put(self, msg: object, block: bool = True) -> bool:
            emitted.append(msg)
            return True

    stage.connect(_Sink(), BackendOutput)
    return stage, latest, emitted


def _imu_until(t_ms: int, after_ms: int) -> ImuBatch:
    t = np.arange(after_ms + 5, t_ms + 1, 5, dtype=np.int64) * MS
    n = len(t)
    return ImuBatch(t, np.zeros((n, 3)), np.tile([0.0, 0.0, 9.81], (n, 1)))


def _estimate(t_ms: int, kf: int) -> Estimate:
    return Estimate.pose_only(t_ms * MS, kf, np.eye(4), True)


def test_estimates_reach_the_front_end_once_the_delay_has_passed_in_sensor_time():
    stage, latest, emitted = _stage(300)
    first, second = _estimate(1000, 0), _estimate(1100, 1)
    stage.on_output(BackendOutput(first, 0, 1.0))
    stage.on_output(BackendOutput(second, 1, 1.0))
    assert [o.estimate for o in emitted] == [first, second]  # downstream: at once
    assert latest.get() is None
    stage.process(_imu_until(1295, 0))
    assert latest.get() is None  # 295 ms after the first keyframe
    stage.process(_imu_until(1300, 1295))
    assert latest.get() is first
    stage.process(_imu_until(1395, 1300))
    assert latest.get() is first
    stage.process(_imu_until(1450, 1395))  # both due: the newer one is the one read
    assert latest.get() is second


def test_no_delay_publishes_at_once():
    stage, latest, _ = _stage(0)
    est = _estimate(1000, 0)
    stage.on_output(BackendOutput(est, 0, 1.0))
    assert latest.get() is est


def test_a_delay_is_for_sequential_runs_only():
    with pytest.raises(ValueError, match="sequential"):
        BackendStage(
            euroc_like_calibration(), BackendConfig(), Latest(), True, False, estimate_delay_ns=MS
        )


def test_a_concurrent_run_with_a_delay_is_a_clear_error():
    """A concurrent run's estimates are as late as its machine makes them: the key is refused
    before anything runs."""
    calib = euroc_like_calibration()
    blank = [np.zeros((480, 752), np.uint8)] * 2
    seq = InMemorySequence("blank", calib, np.array([0, 50 * MS]), blank, blank)
    cfg = preset_config("euroc-stereo-imu")
    cfg.player.sequential_estimate_delay_ms = 500.0
    with pytest.raises(SlamError, match="sequential runs only"):
        run_slam(seq, cfg, None, progress=False)


def test_the_smoother_does_not_read_the_front_ends_poses_once_started():
    """Issue 18: when the back end's estimates reach a monocular front end late, the keyframes
    it sends in the first seconds carry poses in its VO frame or at a stale scale. The smoother
    takes a new state's initial value from its own IMU prediction and its constraints from the
    IMU and the pixel tracks only (the VO pose enters only across an IMU gap), so those poses
    cannot be what collapses its scale (BENCHMARKS.md, monolag20): keyframe poses made
    meaningless after the start (halved, turned, moved) leave every estimate bit-identical."""
    world = generate_world(duration_s=4.0, seed=5, start_s=0.5, landmarks_per_keyframe=100)
    first = _run(world.messages())
    started = [kid for kid, e in first if e.initialized]
    assert started and started[0] < len(world.keyframes) - 10  # started, many keyframes after
    turn = make_transform(Rotation.from_rotvec([0.3, -0.2, 0.5]).as_matrix(), [1.0, -2.0, 0.5])
    stale = []
    for m in world.messages():
        if isinstance(m, Keyframe) and m.keyframe_id > started[0]:
            pose = turn @ m.world_from_body_vo
            pose[:3, 3] *= 0.5
            m = dataclasses.replace(m, world_from_body_vo=pose)
        stale.append(m)
    second = _run(stale)
    assert [k for k, _ in second] == [k for k, _ in first]
    for (_, a), (_, b) in zip(first, second, strict=True):
        assert np.array_equal(a.world_from_body, b.world_from_body)
        assert np.array_equal(a.velocity_world_m_s, b.velocity_world_m_s)


def _run(messages: list[ImuSample | Keyframe]) -> list[tuple[int, Estimate]]:
    be = VioBackend(euroc_like_calibration(distortion=False))
    out = []
    for m in messages:
        if isinstance(m, ImuSample):
            be.add_imu(m)
        else:
            est = be.add_keyframe(m)
            if est is not None:
                out.append((m.keyframe_id, est))
    return out

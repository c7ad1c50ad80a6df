"""A sequential run's back-end estimates delivered late (``player.sequential_estimate_delay_ms``):
each reaches the front end's slot once the IMU stream has passed its keyframe's stamp by the
delay, in order; the outputs downstream are not delayed; 0 publishes at once."""

from __future__ import annotations

import numpy as np
import pytest

from datasets.memory import InMemorySequence
from datasets.rigs import euroc_like_calibration
from slam.backend.config import BackendConfig
from slam.config import preset_config
from slam.core.errors import SlamError
from slam.core.messages import BackendOutput, Estimate, ImuBatch
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

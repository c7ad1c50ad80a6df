"""``backend.keyframe_waits_for_imu``: the back end's stage hands a keyframe to the estimator
only once an IMU reading at or after its stamp has been handed on (at the latest with the next
keyframe, or at the end), so the keyframe interval's last piece is interpolated towards the
next reading instead of holding the last one (BENCHMARKS.md, speedmax21)."""

from __future__ import annotations

from typing import Any

import numpy as np

from datasets.rigs import euroc_like_calibration
from slam.backend.config import BackendConfig
from slam.backend.imu import integration_pieces
from slam.core.messages import BackendFlush, ImuBatch, Keyframe
from slam.runtime.backend import BackendStage
from slam.runtime.stage import Latest
from tests.conftest import pose_keyframe

MS = 1_000_000
OFFSET_NS = 3_000  # the readings come 3 us after the frames, as on the fair V1_01 renders


class _Recorder:
    """Stands in for the estimator: records what the stage hands it."""

    def __init__(self) -> None:
        self.seen: list[Any] = []

    def handle(self, msg: Any) -> list[Any]:
        self.seen.append(msg)
        return []

    def finish(self, interrupted: bool) -> None:
        return None


def _stage(wait: bool) -> tuple[BackendStage, _Recorder]:
    stage = BackendStage(
        euroc_like_calibration(),
        BackendConfig(keyframe_waits_for_imu=wait),
        Latest(),
        False,
        False,
    )
    rec = _Recorder()
    stage._core = rec  # type: ignore[assignment]
    return stage, rec


def _readings(after_ms: int, until_ms: int) -> ImuBatch:
    """The readings a player hands on with the frame at ``until_ms``: those after the previous
    frame, up to this one's stamp (5 ms apart, 3 us after the frames' grid)."""
    t = np.arange(after_ms + 5, until_ms + 1, 5, dtype=np.int64) * MS + OFFSET_NS
    t = t[t <= until_ms * MS]
    n = len(t)
    return ImuBatch(t, np.zeros((n, 3)), np.tile([0.0, 0.0, 9.81], (n, 1)))


def _kf(t_ms: int, kid: int) -> Keyframe:
    return pose_keyframe(t_ms * MS, kid, np.eye(4))


def _order(seen: list[Any]) -> list[str]:
    out = []
    for m in seen:
        if isinstance(m, Keyframe):
            out.append(f"kf{m.keyframe_id}")
        elif isinstance(m, ImuBatch):
            out.append(f"imu..{int(m.t_ns[-1]) // MS}" if len(m) else "imu(empty)")
        elif isinstance(m, BackendFlush):
            out.append("flush")
    return out


def _play(stage: BackendStage, keyframes: dict[int, int], frames_ms: list[int]) -> None:
    """Frames every 50 ms: each one's readings, then (if it is one) its keyframe."""
    prev = frames_ms[0] - 50
    for t in frames_ms:
        stage.process(_readings(prev, t))
        if t in keyframes:
            stage.process(_kf(t, keyframes[t]))
        prev = t


def test_a_keyframe_waits_for_the_reading_after_its_stamp():
    stage, rec = _stage(True)
    _play(stage, {1000: 0, 1100: 1}, [1000, 1050, 1100, 1150])
    # each keyframe goes on right after the readings that pass its stamp (the next frame's)
    assert _order(rec.seen) == ["imu..995", "imu..1045", "kf0", "imu..1095", "imu..1145", "kf1"]
    assert stage.keyframes_waited_for_imu == 2
    assert stage.keyframes_not_covered_by_imu == 0
    # so the estimator can cut the interval's last piece between two readings
    seen = [m for m in rec.seen if isinstance(m, ImuBatch)]
    t = np.concatenate([m.t_ns for m in seen])
    assert t.max() > 1100 * MS


def test_off_a_keyframe_goes_on_at_once():
    stage, rec = _stage(False)
    _play(stage, {1000: 0, 1100: 1}, [1000, 1050, 1100, 1150])
    assert _order(rec.seen) == ["imu..995", "kf0", "imu..1045", "imu..1095", "kf1", "imu..1145"]
    assert stage.keyframes_waited_for_imu == 0


def test_a_keyframe_covered_already_goes_on_at_once_and_one_waits_at_most_until_the_next():
    stage, rec = _stage(True)
    stage.process(_readings(950, 1000))
    stage.process(ImuBatch(np.array([1000 * MS + OFFSET_NS]), np.zeros((1, 3)), np.zeros((1, 3))))
    stage.process(_kf(1000, 0))  # its next reading came first (a lagging back end)
    assert _order(rec.seen)[-1] == "kf0"
    stage.process(_kf(1100, 1))  # no reading past 1000 ms since: waits
    stage.process(_kf(1200, 2))  # the IMU has stopped: kf1 goes on uncovered, kf2 waits
    assert _order(rec.seen)[-1] == "kf1"
    assert stage.keyframes_not_covered_by_imu == 1
    stage.on_end()  # the end hands on the last one before the flush
    assert _order(rec.seen)[-2:] == ["kf2", "flush"]
    assert stage.keyframes_not_covered_by_imu == 2


def test_the_last_piece_held_without_the_next_reading():
    """What the wait is for: without the reading after the stamp, the interval's last piece
    integrates the last reading held; with it, their mean."""
    t = np.array([0, 5, 10], dtype=np.int64) * MS + OFFSET_NS
    acc = np.array([[0.0, 0, 9.0], [0.0, 0, 9.0], [0.0, 0, 11.0]])
    gyro = np.zeros((3, 3))
    t1 = 10 * MS
    held = integration_pieces(t[:2], gyro[:2], acc[:2], 0, t1, 0.1)
    known = integration_pieces(t, gyro, acc, 0, t1, 0.1)
    assert held is not None and known is not None
    assert held[2][-1, 2] == 9.0
    assert abs(known[2][-1, 2] - 10.0) < 1e-3

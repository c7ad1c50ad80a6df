"""Each image's exposure, carried from `slam synth` through our MCAP to the pipeline, which
stamps the image at the middle of its exposure (the time it shows), not at its end."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from datasets import cdr
from datasets.info import sequence_lines
from datasets.mcap_io import McapSequence, write_sequence_mcap
from datasets.memory import random_sequence
from datasets.synth import make_synthetic_sequence
from datasets.synth.camera_model import CameraEffects
from slam.config import preset_config
from slam.core.errors import InputError
from slam.core.messages import ImuSample, StereoFrame
from slam.evaluation.io import read_trajectory
from slam.runtime.player import at_mid_exposure
from slam.runtime.reader import prefetched_messages
from slam.runtime.wiring import run_slam

# auto-exposure over an illumination that swings fast: the exposure moves by milliseconds from
# frame to frame (the aggressive profile is still for its first 2 s: one sub-frame per image)
VARYING = CameraEffects(
    auto_exposure=True, illumination_log_amplitude=1.2, illumination_period_s=1.0
)


@pytest.fixture(scope="module")
def varying():
    seq = make_synthetic_sequence("aggressive", 0.6, 3, camera=VARYING)
    exposure = seq.exposures_ns()
    assert exposure is not None and np.ptp(exposure) > 2_000_000  # it does vary
    return seq


@pytest.fixture(scope="module")
def written(varying, tmp_path_factory: pytest.TempPathFactory) -> Path:
    path = tmp_path_factory.mktemp("exposure") / "ae.mcap"
    write_sequence_mcap(varying, path, progress=False)
    return path


def test_synth_frames_carry_the_exposure_they_were_blurred_over(varying) -> None:
    frames = list(varying.iter_frames())
    want = np.round(varying.exposure.exposure_s * 1e9).astype(np.int64)
    assert [f.exposure_ns for f in frames] == want.tolist()
    # images without blur show the scene at their stamp: no exposure to carry
    assert make_synthetic_sequence("aggressive", 0.2, 3).exposures_ns() is None
    assert make_synthetic_sequence("aggressive", 0.2, 3).frame(0).exposure_ns == 0


def test_mcap_round_trip_keeps_each_frame_exposure(varying, written: Path) -> None:
    back = McapSequence(written)
    assert back.warnings == []
    np.testing.assert_array_equal(back.exposures_ns(), varying.exposures_ns())
    frames = [m for m in back.messages() if isinstance(m, StereoFrame)]
    assert [f.exposure_ns for f in frames] == varying.exposures_ns().tolist()
    assert [f.t_ns for f in frames] == varying.frame_times_ns().tolist()  # stamps untouched
    n = back.num_frames
    assert f"  exposure recorded for {n}/{n} frames" in "\n".join(sequence_lines(back))
    # through the reader process too (the images in shared memory, the exposure in the bundle)
    far = [m for m in prefetched_messages(McapSequence(written)) if isinstance(m, StereoFrame)]
    assert [f.exposure_ns for f in far] == varying.exposures_ns().tolist()


def test_files_without_exposure_read_as_unknown(tmp_path: Path) -> None:
    path = tmp_path / "plain.mcap"
    write_sequence_mcap(random_sequence(num_frames=4, seed=2), path, progress=False)
    back = McapSequence(path)
    assert back.exposures_ns() is None and "/cam0/exposure" not in back.scan.topics()
    assert all(f.exposure_ns == 0 for f in back.iter_frames())


def test_exposure_message_is_a_standard_time_reference() -> None:
    """rosbags (independent) decodes it: time_ref = the exposure's start; ours decodes back."""
    from rosbags.typesys import Stores, get_typestore

    ts = get_typestore(Stores.ROS2_HUMBLE)
    data = cdr.encode_exposure(12_000_000_007, "cam0", 4_093_250)
    msg = ts.deserialize_cdr(data, "sensor_msgs/msg/TimeReference")
    assert msg.header.stamp.sec == 12 and msg.header.stamp.nanosec == 7
    assert msg.time_ref.sec * 10**9 + msg.time_ref.nanosec == 12_000_000_007 - 4_093_250
    assert msg.source == "exposure_start"
    assert bytes(ts.serialize_cdr(msg, "sensor_msgs/msg/TimeReference")) == data
    assert cdr.decode_exposure(data) == (12_000_000_007, 4_093_250)
    msg.source = "gps"
    with pytest.raises(InputError, match="exposure_start"):
        cdr.decode_exposure(bytes(ts.serialize_cdr(msg, "sensor_msgs/msg/TimeReference")))


def _frame(t_ns: int, exposure_ns: int) -> StereoFrame:
    return StereoFrame(t_ns, np.zeros((2, 2), np.uint8), None, exposure_ns=exposure_ns)


def test_at_mid_exposure_moves_frames_only() -> None:
    imu = [ImuSample(t, np.zeros(3), np.zeros(3)) for t in (0, 5, 10)]
    msgs = [imu[0], _frame(10, 8), imu[1], _frame(20, 0), imu[2], _frame(30, 7)]
    out = list(at_mid_exposure(iter(msgs)))
    assert [m.t_ns for m in out] == [0, 6, 5, 20, 10, 27]  # 10 - 8/2, unknown kept, 30 - 7//2
    assert [m.exposure_ns for m in out if isinstance(m, StereoFrame)] == [8, 0, 7]
    # stamps stay increasing even if an exposure grows faster than the frame period
    frames = list(at_mid_exposure(iter([_frame(10, 0), _frame(12, 10)])))
    assert [f.t_ns for f in frames] == [10, 11]


@pytest.mark.parametrize("mid_exposure", [True, False])
def test_the_pipeline_uses_the_middle_of_the_exposure(varying, tmp_path, mid_exposure) -> None:
    """Every output row is at the time the image shows: stamp - exposure / 2 (the switch off:
    the driver's stamp)."""
    cfg = preset_config("stereo-vo")
    cfg.player.sequential = True
    cfg.player.speed = 0.0
    cfg.player.mid_exposure = mid_exposure
    run_slam(varying, cfg, tmp_path / "run", progress=False)
    t_ns = read_trajectory(tmp_path / "run" / "trajectory.tum").trajectory.t_ns
    stamps = varying.frame_times_ns()
    want = stamps - varying.exposures_ns() // 2 if mid_exposure else stamps
    np.testing.assert_array_equal(t_ns, want)


def test_sequence_image_times_are_the_middle_of_each_exposure(varying) -> None:
    want = varying.frame_times_ns() - varying.exposures_ns() // 2
    np.testing.assert_array_equal(varying.image_times_ns(), want)
    assert [f.mid_exposure_ns for f in varying.iter_frames()] == want.tolist()
    clean = make_synthetic_sequence("aggressive", 0.2, 3)  # no exposure recorded: the stamps
    np.testing.assert_array_equal(clean.image_times_ns(), clean.frame_times_ns())


def test_fuse_poses_each_image_at_the_middle_of_its_exposure(varying, written, monkeypatch) -> None:
    """`slam fuse` looks up each image's pose at the time it shows, as `slam run` stamps it."""
    from mapping.fuse import fuse_sequence
    from mapping.mapper import DenseMapper, MapperConfig

    seen: list[int] = []
    add = DenseMapper.add_keyframe

    def spy(self, t_ns, *args, **kwargs):  # type: ignore[no-untyped-def]
        seen.append(t_ns)
        return add(self, t_ns, *args, **kwargs)

    monkeypatch.setattr(DenseMapper, "add_keyframe", spy)
    fuse_sequence(written, None, MapperConfig(), every=3, max_frames=3, progress=False)
    # frame 0 shows the scene before the ground truth's first pose: no pose, skipped
    assert seen == varying.image_times_ns()[[3, 6]].tolist()

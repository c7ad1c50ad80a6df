"""`slam calib check`: the camera-IMU time offset and rotation recovered from synthetic recordings
with injected errors, and one-line answers where the data cannot tell (still real EuRoC frames,
one-axis rotation, an offset beyond the search range, no IMU)."""

from __future__ import annotations

import json

import numpy as np
import pytest
from conftest import require

from datasets.mcap_io import write_sequence_mcap
from datasets.open import open_sequence
from datasets.synth import make_synthetic_sequence
from slam.calib.check import (
    CalibCheck,
    CalibrationUnobservable,
    GyroIntegral,
    check_calibration,
    estimate_camera_rotation,
    estimate_time_offset,
    refine_time_offset,
)
from slam.calib.visual_rotation import VisualRotations, visual_rotations
from slam.core.errors import InputError
from slam.core.geometry import rotation_angle_rad
from tools.cli import main

OFFSET_NS = 15_000_000


@pytest.fixture(scope="module")
def late(tmp_path_factory):
    """8 s of the aggressive profile, images 15 ms late, calibration's rotation 2 deg off."""
    seq = make_synthetic_sequence(
        "aggressive", 8.0, 2, time_offset_ns=OFFSET_NS, calib_rotation_error_deg=(0.0, 2.0, 0.0)
    )
    path = tmp_path_factory.mktemp("calib") / "late.mcap"
    write_sequence_mcap(seq, path, progress=False)
    return seq, path


@pytest.fixture(scope="module")
def vis(late) -> VisualRotations:
    _, path = late
    back = open_sequence(path)
    return visual_rotations(
        ((f.t_ns, f.left) for f in back.iter_frames()), back.calibration.cam0.intrinsics
    )


def _solve(vis: VisualRotations, gyro: GyroIntegral, max_offset_ns: int = 100_000_000):
    coarse = estimate_time_offset(vis, gyro, max_offset_ns)
    rot = estimate_camera_rotation(vis, gyro, coarse.offset_ns)
    fine = refine_time_offset(vis, gyro, coarse, rot.body_from_cam_rot)
    return fine, estimate_camera_rotation(vis, gyro, fine.offset_ns)


@pytest.mark.parametrize("true_offset_ms", [-30, -12, 0, 7, 30])
def test_time_offset_recovered_to_a_millisecond(late, vis, true_offset_ms: int) -> None:
    """The same images against the IMU with its stamps moved: any injected offset comes back."""
    seq, _ = late
    imu = seq.imu()
    shift_ns = OFFSET_NS - true_offset_ms * 1_000_000  # IMU stamps earlier by this much
    offset, rotation = _solve(vis, GyroIntegral(imu.t_ns - shift_ns, imu.gyro_rad_s))
    assert abs(offset.offset_ns * 1e-6 - true_offset_ms) <= 1.0, offset
    assert offset.std_ns < 1_000_000
    true_rot = seq.true_calibration.cam0.body_from_cam[:3, :3]
    assert np.degrees(rotation_angle_rad(rotation.body_from_cam_rot @ true_rot.T)) <= 0.5


def test_cli_flags_offset_and_rotation_error(late, tmp_path, capsys) -> None:
    seq, path = late
    out = tmp_path / "check.json"
    assert main(["calib", "check", str(path), "--json", str(out), "-q"]) == 1
    text = capsys.readouterr().out
    assert "time offset +1" in text and "WRONG" in text and "timeshift_cam_imu" in text
    res = json.loads(out.read_text())
    assert abs(res["time_offset"]["total_ms"] - 15.0) <= 1.0
    assert res["time_offset"]["flagged"] and res["rotation"]["flagged"] and not res["ok"]
    assert abs(res["rotation"]["error_deg"] - 2.0) <= 0.5
    est = np.array(res["rotation"]["body_from_cam0_rot"])
    true_rot = seq.true_calibration.cam0.body_from_cam[:3, :3]
    assert np.degrees(rotation_angle_rad(est @ true_rot.T)) <= 0.5


def test_right_calibration_passes(late, vis) -> None:
    seq, _ = late
    imu = seq.imu()
    gyro = GyroIntegral(imu.t_ns - OFFSET_NS, imu.gyro_rad_s)  # offset 0
    offset, rotation = _solve(vis, gyro)
    check = CalibCheck(
        offset, rotation, 0, seq.true_calibration.cam0.body_from_cam[:3, :3], duration_s=8.0
    )
    assert check.ok, check.report()
    assert all(line.endswith("OK") for line in check.report()[1:])


def test_offset_beyond_search_range_is_an_answer_not_a_number(late, vis) -> None:
    seq, _ = late
    imu = seq.imu()
    gyro = GyroIntegral(imu.t_ns - OFFSET_NS + 80_000_000, imu.gyro_rad_s)  # true -80 ms
    with pytest.raises(CalibrationUnobservable, match="edge of the search range"):
        estimate_time_offset(vis, gyro, 50_000_000)


def test_rotation_about_one_axis_is_unobservable() -> None:
    t_imu = np.arange(0, 20_000_000_001, 5_000_000, dtype=np.int64)
    rate = 1.0 * np.sin(2 * np.pi * 0.3 * t_imu * 1e-9)
    gyro = np.stack([np.zeros_like(rate), np.zeros_like(rate), rate], axis=1)
    integral = GyroIntegral(t_imu, gyro)
    t0 = np.arange(200_000_000, 19_000_000_000, 50_000_000, dtype=np.int64)
    t1 = t0 + 50_000_000
    vis = VisualRotations(t0, t1, integral.rotvec(t0, t1), np.full(len(t0), 100), len(t0))
    assert estimate_time_offset(vis, integral).offset_ns == pytest.approx(0.0, abs=2e5)
    with pytest.raises(CalibrationUnobservable, match="one axis"):
        estimate_camera_rotation(vis, integral, 0.0)


def test_still_real_euroc_frames_say_too_little_motion(shared_data, capsys) -> None:
    seq = require(shared_data / "euroc_v101_micro")
    assert main(["calib", "check", str(seq), "-q"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert "too little motion" in err[-1] and err[-1].startswith("slam calib: error:")


def test_no_imu_is_an_input_error() -> None:
    seq = make_synthetic_sequence("figure8", 0.5)
    with pytest.raises(InputError, match="no IMU"):
        check_calibration(iter(()), np.zeros(0, np.int64), np.zeros((0, 3)), seq.calibration)


def _gyro_only_rotations(rate_amplitude_rad_s: float) -> tuple[VisualRotations, GyroIntegral]:
    """Frame-pair rotations of a rig turning about two axes at the given amplitude, 20 s."""
    t_imu = np.arange(0, 20_000_000_001, 5_000_000, dtype=np.int64)
    t_s = t_imu * 1e-9
    gyro = rate_amplitude_rad_s * np.stack(
        [np.sin(2 * np.pi * 0.3 * t_s), np.cos(2 * np.pi * 0.2 * t_s), np.zeros_like(t_s)], axis=1
    )
    integral = GyroIntegral(t_imu, gyro)
    t0 = np.arange(200_000_000, 19_000_000_000, 50_000_000, dtype=np.int64)
    t1 = t0 + 50_000_000
    vis = VisualRotations(t0, t1, integral.rotvec(t0, t1), np.full(len(t0), 100), len(t0))
    return vis, integral


@pytest.mark.parametrize(
    ("amplitude_rad_s", "what"), [(0.0, "still"), (0.05, "too little rotation")]
)
def test_still_or_slowly_turning_rig_is_an_answer_not_a_number(
    amplitude_rad_s: float, what: str
) -> None:
    """A still rig and one turning at 0.05 rad/s: "too little motion", never an offset."""
    vis, gyro = _gyro_only_rotations(amplitude_rad_s)
    with pytest.raises(CalibrationUnobservable, match="too little motion") as err:
        estimate_time_offset(vis, gyro)
    assert "\n" not in str(err.value), what
    with pytest.raises(CalibrationUnobservable, match="too little motion"):
        estimate_camera_rotation(vis, gyro, 0.0)
    # the same rig turning at 1 rad/s gives its (zero) offset back: the answer is about motion
    vis, gyro = _gyro_only_rotations(1.0)
    assert abs(estimate_time_offset(vis, gyro).offset_ns) < 2e5


def test_exposure_is_not_mistaken_for_an_offset(tmp_path) -> None:
    """Images blurred over 12 ms ending at their stamps, no offset: taken at the middle of the
    exposure (recorded in our MCAP), the check finds none (at the stamps it found -5.9 ms)."""
    from datasets.synth.camera_model import CameraEffects

    seq = make_synthetic_sequence("aggressive", 6.0, 2, camera=CameraEffects(exposure_s=0.012))
    path = tmp_path / "blurred.mcap"
    write_sequence_mcap(seq, path, progress=False)
    out = tmp_path / "check.json"
    assert main(["calib", "check", str(path), "--json", str(out), "-q"]) == 0
    assert abs(json.loads(out.read_text())["time_offset"]["total_ms"]) <= 1.0

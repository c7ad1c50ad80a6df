"""EuRoC / TUM-VI ASL folders: the shared V1_01 micro folder and small generated ones."""

from __future__ import annotations

import re
from pathlib import Path

import cv2
import numpy as np
import pytest
from conftest import require

from datasets.euroc import (
    EurocSequence,
    read_euroc_groundtruth_full,
    read_trajectory_file,
)
from datasets.mcap_io import McapSequence
from datasets.memory import random_sequence
from datasets.open import open_sequence
from slam.core.geometry import invert_transform
from tools.cli import main as slam_main


@pytest.fixture(scope="module")
def micro(shared_data: Path) -> Path:
    return require(shared_data / "euroc_v101_micro")


def opencv_yaml(path: Path, key: str) -> np.ndarray:
    """Independent reader: OpenCV's FileStorage understands the %YAML:1.0 sensor.yaml files."""
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    node = fs.getNode(key)
    if node.isMap():  # EuRoC's T_BS: {cols, rows, data: [...]}
        rows = int(node.getNode("rows").real())
        node = node.getNode("data")
        out = np.array([node.at(i).real() for i in range(node.size())]).reshape(rows, -1)
    else:
        out = np.array([node.at(i).real() for i in range(node.size())])
    fs.release()
    return out


def test_micro_counts_and_calibration(micro: Path) -> None:
    seq = open_sequence(micro)
    assert isinstance(seq, EurocSequence)
    assert seq.num_frames == 95
    assert seq.num_imu == 29_120
    # cam1/data.csv lists 4 extra rows without images: reported, not silently dropped
    assert any("4 cam1" in w for w in seq.warnings)
    cal = seq.calibration
    assert cal.is_stereo
    for cam in cal.cameras:
        yaml_path = micro / "mav0" / cam.name / "sensor.yaml"
        fu, fv, cu, cv = opencv_yaml(yaml_path, "intrinsics")
        i = cam.intrinsics
        assert (i.fx, i.fy, i.cx, i.cy) == (fu, fv, cu, cv)
        assert (i.width, i.height) == (752, 480)
        assert i.distortion_model == "radtan"
        np.testing.assert_array_equal(
            i.distortion, opencv_yaml(yaml_path, "distortion_coefficients")
        )
        T_BS = opencv_yaml(yaml_path, "T_BS")  # noqa: N806 - imu0's T_BS is identity
        np.testing.assert_array_equal(cam.body_from_cam, T_BS)
    assert cal.cam0.intrinsics.fx == 458.654 and cal.cameras[1].intrinsics.cx == 379.999
    assert abs(cal.stereo_baseline_m() - 0.110) < 0.001  # EuRoC's 11 cm baseline
    assert cal.imu is not None
    assert cal.imu.gyro_noise_density == 1.6968e-04 and cal.imu.accel_random_walk == 3.0e-3
    assert cal.imu.rate_hz == 200.0


def test_micro_data_exact(micro: Path) -> None:
    seq = EurocSequence(micro)
    mav0 = micro / "mav0"
    first_cam = (mav0 / "cam0" / "data.csv").read_text().splitlines()[1].split(",")
    assert seq.frame_times_ns()[0] == int(first_cam[0]) == 1403715273262142976
    f = seq.frame(10)
    ref = cv2.imread(str(mav0 / "cam1" / "data" / f"{f.t_ns}.png"), cv2.IMREAD_UNCHANGED)
    assert f.right is not None and f.right.dtype == np.uint8 and np.array_equal(f.right, ref)
    imu = seq.imu()
    row = (mav0 / "imu0" / "data.csv").read_text().splitlines()[1].split(",")
    assert imu.t_ns[0] == int(row[0])
    np.testing.assert_array_equal(imu.gyro_rad_s[0], [float(x) for x in row[1:4]])
    np.testing.assert_array_equal(imu.accel_m_s2[0], [float(x) for x in row[4:7]])
    assert abs(np.median(np.diff(imu.t_ns)) - 5_000_000) < 1000
    assert seq.ground_truth is None  # the micro folder lacks state_groundtruth_estimate0/data.csv


def test_micro_ground_truth_files(micro: Path) -> None:
    gt_csv = micro / "groundtruth_openvins" / "V1_01_easy.csv"
    traj, vel, bg, ba = read_euroc_groundtruth_full(gt_csv)
    assert len(traj) == 2895 and vel.shape == bg.shape == ba.shape == (2895, 3)
    row = gt_csv.read_text().splitlines()[1].split(",")
    assert traj.t_ns[0] == int(row[0])
    np.testing.assert_allclose(bg[0], [float(x) for x in row[11:14]])
    np.testing.assert_allclose(ba[0], [float(x) for x in row[14:17]])
    # the TUM text version of the same trajectory agrees (time parsed without float rounding)
    tum = read_trajectory_file(micro / "groundtruth_openvins" / "V1_01_easy.txt")
    assert len(tum) == len(traj)
    assert np.max(np.abs(tum.t_ns - traj.t_ns)) <= 5_000  # the txt keeps 10 us digits
    np.testing.assert_allclose(tum.positions_m, traj.positions_m, atol=1e-6)
    dots = np.abs(np.sum(tum.q_wxyz * traj.q_wxyz, axis=1))
    assert np.all(dots > 1 - 1e-9)
    seq = open_sequence(micro, gt_path=gt_csv)
    assert seq.ground_truth is not None and len(seq.ground_truth) == 2895


def test_micro_convert_round_trip(
    micro: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """`slam convert` of the folder, then `slam info` and a read back of the file."""
    seq = EurocSequence(micro)
    out = tmp_path / "micro.mcap"
    assert slam_main(["convert", str(micro), str(out), "-q"]) == 0
    assert "wrote" in capsys.readouterr().out
    assert slam_main(["info", str(out)]) == 0
    info = capsys.readouterr().out
    assert re.search(r"frames +95 stereo +20.00 Hz", info)
    assert re.search(r"imu +29120 +200.00 Hz", info)
    assert "stereo baseline 11.0" in info
    back = McapSequence(out)
    assert back.num_frames == 95 and back.num_imu == 29_120
    np.testing.assert_array_equal(back.frame_times_ns(), seq.frame_times_ns())
    np.testing.assert_array_equal(back.imu().accel_m_s2, seq.imu().accel_m_s2)
    for i in (0, 47, 94):
        a, b = back.frame(i), seq.frame(i)
        assert np.array_equal(a.left, b.left) and np.array_equal(a.right, b.right)
    assert back.calibration.to_dict() == seq.calibration.to_dict()


def write_asl_folder(
    root: Path, *, equidistant: bool = False, gt_folder: str = "state_groundtruth_estimate0"
) -> object:
    """A small ASL folder (TUM-VI flavour when ``equidistant``) from a random sequence."""
    seq = random_sequence(num_frames=6, width=64, height=48, seed=5)
    mav0 = root / "mav0"
    cam_T_BS = []
    for k, name in enumerate(("cam0", "cam1")):
        d = mav0 / name / "data"
        d.mkdir(parents=True)
        lines = ["#timestamp [ns],filename"]
        for f in seq.iter_frames():
            img = f.left if k == 0 else f.right
            cv2.imwrite(str(d / f"{f.t_ns}.png"), img)
            lines.append(f"{f.t_ns},{f.t_ns}.png")
        (mav0 / name / "data.csv").write_text("\n".join(lines) + "\n")
        T_BS = seq.calibration.cameras[k].body_from_cam  # noqa: N806
        cam_T_BS.append(T_BS)
        model, coeffs = (
            ("equidistant", "[0.01, -0.002, 0.001, -0.0003]")
            if equidistant
            else ("radial-tangential", "[-0.28, 0.07, 0.0002, 1.7e-05]")
        )
        (mav0 / name / "sensor.yaml").write_text(
            "%YAML:1.0\ncamera_model: pinhole\nrate_hz: 20\nresolution: [64, 48]\n"
            "intrinsics: [40.0, 41.0, 32.0, 24.0]\n"
            f"distortion_model: {model}\ndistortion_coefficients: {coeffs}\n"
            f"T_BS:\n  cols: 4\n  rows: 4\n  data: {T_BS.reshape(-1).tolist()}\n"
        )
    imu = seq.imu()
    (mav0 / "imu0").mkdir()
    rows = ["#timestamp [ns],wx,wy,wz,ax,ay,az"] + [
        f"{t}," + ",".join(repr(float(x)) for x in np.r_[g, a])
        for t, g, a in zip(imu.t_ns, imu.gyro_rad_s, imu.accel_m_s2)
    ]
    (mav0 / "imu0" / "data.csv").write_text("\n".join(rows) + "\n")
    (mav0 / "imu0" / "sensor.yaml").write_text(
        "%YAML:1.0\nrate_hz: 200\ngyroscope_noise_density: 0.00016\n"
        "gyroscope_random_walk: 2.2e-05\naccelerometer_noise_density: 0.0028\n"
        "accelerometer_random_walk: 0.00086\n"
    )
    gt = seq.ground_truth
    assert gt is not None
    (mav0 / gt_folder).mkdir()
    rows = ["#timestamp,px,py,pz,qw,qx,qy,qz"] + [
        f"{t}," + ",".join(repr(float(x)) for x in np.r_[p, q])
        for t, p, q in zip(gt.t_ns, gt.positions_m, gt.q_wxyz)
    ]
    (mav0 / gt_folder / "data.csv").write_text("\n".join(rows) + "\n")
    return seq


def test_tumvi_style_folder(tmp_path: Path) -> None:
    ref = write_asl_folder(tmp_path, equidistant=True, gt_folder="mocap0")
    seq = open_sequence(tmp_path)
    assert seq.warnings == []
    assert seq.num_frames == 6
    cal = seq.calibration
    assert cal.cam0.intrinsics.distortion_model == "equidistant"
    assert cal.cam0.intrinsics.distortion == (0.01, -0.002, 0.001, -0.0003)
    np.testing.assert_allclose(
        cal.cameras[1].body_from_cam, ref.calibration.cameras[1].body_from_cam
    )  # type: ignore[attr-defined]
    assert cal.imu is not None and cal.imu.accel_noise_density == 0.0028
    for a, b in zip(seq.iter_frames(), ref.iter_frames(), strict=True):  # type: ignore[attr-defined]
        assert (
            a.t_ns == b.t_ns and np.array_equal(a.left, b.left) and np.array_equal(a.right, b.right)
        )
    np.testing.assert_array_equal(seq.imu().gyro_rad_s, ref.imu().gyro_rad_s)  # type: ignore[attr-defined]
    assert seq.ground_truth is not None
    np.testing.assert_array_equal(seq.ground_truth.t_ns, ref.ground_truth.t_ns)  # type: ignore[attr-defined]
    np.testing.assert_allclose(seq.ground_truth.positions_m, ref.ground_truth.positions_m)  # type: ignore[attr-defined]


def test_imu_T_BS_moves_cameras_and_ground_truth_to_imu(tmp_path: Path) -> None:  # noqa: N802
    """With a non-identity imu0 T_BS the body frame becomes the IMU frame."""
    write_asl_folder(tmp_path)
    B_from_imu = np.eye(4)  # noqa: N806
    B_from_imu[:3, 3] = [0.1, -0.2, 0.05]
    yaml_path = tmp_path / "mav0" / "imu0" / "sensor.yaml"
    yaml_path.write_text(
        yaml_path.read_text() + f"T_BS:\n  data: {B_from_imu.reshape(-1).tolist()}\n"
    )
    plain = EurocSequence(tmp_path)  # cameras read relative to B, then moved to the IMU
    cam0_T_BS = opencv_yaml(tmp_path / "mav0" / "cam0" / "sensor.yaml", "T_BS")  # noqa: N806
    np.testing.assert_allclose(
        plain.calibration.cam0.body_from_cam, invert_transform(B_from_imu) @ cam0_T_BS
    )
    assert plain.ground_truth is not None
    gt_raw = read_trajectory_file(tmp_path / "mav0" / "state_groundtruth_estimate0" / "data.csv")
    np.testing.assert_allclose(
        plain.ground_truth.matrices(), gt_raw.matrices() @ B_from_imu, atol=1e-12
    )


def test_unordered_csv_rows_are_sorted_and_counted(tmp_path: Path) -> None:
    ref = write_asl_folder(tmp_path)
    csv = tmp_path / "mav0" / "imu0" / "data.csv"
    lines = csv.read_text().splitlines()
    lines[5], lines[6] = lines[6], lines[5]  # one pair swapped
    lines.insert(9, lines[9])  # one row repeated
    csv.write_text("\n".join(lines) + "\n")
    seq = EurocSequence(tmp_path)
    assert (
        "imu0/data.csv: 1 out of time order (sorted), 1 with duplicate timestamps (dropped)"
        in seq.warnings
    )
    np.testing.assert_array_equal(seq.imu().t_ns, ref.imu().t_ns)  # type: ignore[attr-defined]
    np.testing.assert_array_equal(seq.imu().accel_m_s2, ref.imu().accel_m_s2)  # type: ignore[attr-defined]


def test_overlap_line_counts_what_a_run_uses() -> None:
    from datasets.info import overlap_line

    s = 1_000_000_000
    frames = np.arange(10, 15) * s  # 10 .. 14 s
    imu = np.arange(0, 101) * s // 10  # 0 .. 10 s: only the first frame has IMU
    assert overlap_line(frames, np.arange(0, 301) * s // 10) == (
        "  overlap  10.000 .. 14.000 s (4.00 s) of frames and IMU: what a run uses "
        "(26.00 s of IMU outside the frames are not used)"
    )
    assert overlap_line(frames, imu) == (
        "  overlap  10.000 .. 10.000 s (0.00 s) of frames and IMU: what a run uses (4 frames "
        "outside it have no IMU; 10.00 s of IMU outside the frames are not used)"
    )
    assert overlap_line(frames, imu[:50]).startswith("  overlap  none: the IMU misses the frames")
    assert overlap_line(frames, imu[:0]) == (
        "  overlap  none: no IMU, a run uses the frames alone, 10.000 .. 14.000 s (4.00 s)"
    )


def test_info_names_ground_truth_files_beside_the_folder(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Ground truth outside mav0/: `slam info` lists it (poses, coverage) and says --gt."""
    write_asl_folder(tmp_path)
    mav0 = tmp_path / "mav0"
    (tmp_path / "groundtruth").mkdir()
    (mav0 / "state_groundtruth_estimate0" / "data.csv").rename(tmp_path / "groundtruth" / "a.csv")
    (tmp_path / "notes.txt").write_text("not a trajectory\n")
    assert slam_main(["info", str(tmp_path)]) == 0
    out = capsys.readouterr().out
    assert (
        "ground truth: none in the sequence; trajectory files in its folder (pass one with "
        f"--gt FILE):\n  {tmp_path / 'groundtruth' / 'a.csv'}: "
    ) in out
    assert "covers 6/6 frames" in out and "notes.txt" not in out and "imu0" not in out
    gt = tmp_path / "groundtruth" / "a.csv"
    assert slam_main(["info", str(tmp_path), "--gt", str(gt)]) == 0
    assert re.search(r"ground truth: \d+ poses, .* covers 6/6 frames", capsys.readouterr().out)
    (gt).unlink()
    assert slam_main(["info", str(tmp_path)]) == 0
    assert "ground truth: none; pass one with --gt FILE (EuRoC csv or TUM text)" in (
        capsys.readouterr().out
    )


def test_info_micro_spans_and_ground_truth(micro: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """The micro folder: 4.7 s of images in 145.6 s of IMU, ground truth in a subfolder."""
    assert slam_main(["info", str(micro)]) == 0
    out = capsys.readouterr().out
    assert "duration 145" not in out
    assert "(4.70 s) of frames and IMU: what a run uses (140.90 s of IMU outside" in out
    gt = micro / "groundtruth_openvins"
    for name, poses, covers in (
        ("V1_01_easy.csv", 2895, "95/95"),
        ("V1_01_easy.txt", 2895, "95/95"),
        ("V1_01_easy_original.txt", 28712, "74/95"),
    ):
        line = next(x for x in out.splitlines() if x.startswith(f"  {gt / name}: "))
        assert line.endswith(f"covers {covers} frames") and f": {poses} poses, " in line


def test_run_goes_on_past_a_missing_image(micro: Path, tmp_path: Path) -> None:
    """The micro folder, linked file by file into tmp_path with one left image gone: the run
    skips that frame, names it in stats.json, and tracks the others."""
    import json

    src, dst = micro / "mav0", tmp_path / "seq" / "mav0"
    for name in ("cam0", "cam1"):
        (dst / name / "data").mkdir(parents=True)
        for f in ("data.csv", "sensor.yaml"):
            (dst / name / f).symlink_to(src / name / f)
    (dst / "imu0").symlink_to(src / "imu0")
    times = EurocSequence(micro).frame_times_ns()
    for t in times:
        for name in ("cam0", "cam1"):
            (dst / name / "data" / f"{t}.png").symlink_to(src / name / "data" / f"{t}.png")
    missing = dst / "cam0" / "data" / f"{times[5]}.png"
    missing.unlink()
    out = tmp_path / "run"
    argv = ["run", str(tmp_path / "seq"), "--out", str(out), "--max-frames", "11"]
    assert slam_main([*argv, "--speed", "max", "--config", "stereo-vo", "--no-progress"]) == 0
    stats = json.loads((out / "stats.json").read_text())
    assert stats["frames_in"] == 11
    skipped = [w for w in stats["sequence_warnings"] if "frame(s) skipped" in w]
    assert skipped == [
        f"1 frame(s) skipped: image file missing: cam0/{times[5]}.png (listed in data.csv; "
        "--strict refuses the folder instead)"
    ]
    tracked = np.loadtxt(out / "trajectory.tum")[:, 0]
    assert len(tracked) == 11 and not np.any(np.abs(tracked - times[5] * 1e-9) < 1e-4)

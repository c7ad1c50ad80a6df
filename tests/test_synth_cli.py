"""`slam synth`: writes a readable MCAP (bit-identical images, equal IMU), depth PNGs and a PLY
of the scene; user mistakes end in one line and exit status 2."""

from __future__ import annotations

import cv2
import numpy as np

from datasets.open import open_sequence
from datasets.ply import read_ply
from datasets.synth import make_synthetic_sequence
from datasets.synth.export import depth_image_name, read_depth_folder
from tools.cli import main


def test_synth_cli_writes_mcap_depth_and_mesh(tmp_path) -> None:
    out = tmp_path / "a.mcap"
    rc = main(
        [
            "synth", str(out), "--duration", "0.5", "--seed", "4", "--mesh",
            str(tmp_path / "scene.ply"), "--depth-dir", str(tmp_path / "depth"), "-q",
        ]
    )  # fmt: skip
    assert rc == 0 and out.is_file()
    ref = make_synthetic_sequence("figure8", duration_s=0.5, seed=4)
    back = open_sequence(out)
    assert back.num_frames == ref.num_frames == 11
    assert np.array_equal(back.imu().t_ns, ref.imu().t_ns)
    assert np.allclose(back.imu().accel_m_s2, ref.imu().accel_m_s2, rtol=0, atol=1e-12)
    for i in (0, 7):
        a, b = back.frame(i), ref.frame(i)
        assert a.t_ns == b.t_ns
        assert np.array_equal(a.left, b.left) and np.array_equal(a.right, b.right)
    assert back.ground_truth is not None and len(back.ground_truth) == len(ref.ground_truth)
    ply = read_ply(tmp_path / "scene.ply")
    verts, tris = ply.points, ply.faces
    v_ref, t_ref = ref.scene_mesh()
    assert np.allclose(verts, v_ref, atol=1e-5) and np.array_equal(tris, t_ref)
    t7 = int(ref.frame_times_ns()[7])
    depth_mm = cv2.imread(str(tmp_path / "depth" / f"{t7:019d}.png"), cv2.IMREAD_UNCHANGED)
    assert depth_mm.dtype == np.uint16
    assert np.abs(depth_mm * 1e-3 - ref.depth(7)).max() <= 0.0005 + 1e-6
    assert (tmp_path / "depth" / "depth.json").is_file()
    # names sort in time order (zero-padded, 19 digits as EuRoC's) and read back in order
    names = sorted(p.name for p in (tmp_path / "depth").glob("*.png"))
    assert names[:2] == ["0000000000000000000.png", "0000000000050000000.png"]
    t_ns, paths = read_depth_folder(tmp_path / "depth")
    np.testing.assert_array_equal(t_ns, ref.frame_times_ns())
    assert [p.name for p in paths] == names


def test_depth_folder_reads_old_unpadded_names(tmp_path) -> None:
    """Folders written before the names were padded (``0.png``, ``100000000.png``) still read,
    in time order, not name order."""
    for t in (0, 50_000_000, 100_000_000, 1_000_000_000):
        (tmp_path / f"{t}.png").write_bytes(b"")
    (tmp_path / "depth.json").write_text("{}")
    t_ns, paths = read_depth_folder(tmp_path)
    assert t_ns.tolist() == [0, 50_000_000, 100_000_000, 1_000_000_000]
    assert [p.name for p in paths] == ["0.png", "50000000.png", "100000000.png", "1000000000.png"]
    assert depth_image_name(50_000_000) == "0000000000050000000.png"


def test_synth_cli_user_errors_exit_2(tmp_path, capsys) -> None:
    assert main(["synth", str(tmp_path / "b.mcap"), "--blackout", "x"]) == 2
    assert "--blackout" in capsys.readouterr().err
    assert main(["synth", str(tmp_path / "b.mcap"), "--imu-csv", "imu.csv"]) == 2
    missing = str(tmp_path / "none.csv")
    assert main(["synth", str(tmp_path / "b.mcap"), "--from-trajectory", missing]) == 2
    assert "not found" in capsys.readouterr().err
    assert main(["synth", str(tmp_path / "b.mcap"), "--gyro-bias", "1,2"]) == 2
    assert not (tmp_path / "b.mcap").exists()


def test_synth_cli_initial_biases(tmp_path) -> None:
    out = tmp_path / "bias.mcap"
    args = ["synth", str(out), "--duration", "0.2", "--no-imu-noise", "-q"]
    assert main([*args, "--gyro-bias", "0.01,-0.02,0.03", "--accel-bias", "0.1,0.2,-0.3"]) == 0
    ref = make_synthetic_sequence("figure8", duration_s=0.2, imu_noise=False)
    back = open_sequence(out)
    assert np.allclose(back.imu().gyro_rad_s - ref.imu().gyro_rad_s, [0.01, -0.02, 0.03])
    assert np.allclose(back.imu().accel_m_s2 - ref.imu().accel_m_s2, [0.1, 0.2, -0.3])


def test_synth_cli_camera_effects(tmp_path, capsys) -> None:
    """`--camera realistic` with overrides writes what the library makes with the same effects;
    out-of-range effects are one-line errors."""
    from datasets.synth.camera_model import realistic_camera
    from datasets.synth.imu_sim import realistic_imu

    out = tmp_path / "real.mcap"
    args = ["synth", str(out), "--duration", "0.3", "--camera", "realistic", "-q"]
    assert main([*args, "--time-offset", "12.5", "--vignetting", "0.2", "--line-delay", "20"]) == 0
    ref = make_synthetic_sequence(
        "figure8",
        duration_s=0.3,
        camera=realistic_camera().replace(vignetting=0.2, line_delay_s=20e-6),
        imu_effects=realistic_imu(),
        time_offset_ns=12_500_000,
    )
    back = open_sequence(out)
    assert back.calibration.time_offset_ns == 0
    np.testing.assert_array_equal(back.frame(3).left, ref.frame(3).left)
    np.testing.assert_array_equal(back.frame(3).right, ref.frame(3).right)
    np.testing.assert_allclose(back.imu().accel_m_s2, ref.imu().accel_m_s2, atol=1e-12)
    for bad in (["--vignetting", "1.5"], ["--imu-vibration", "1,2"], ["--time-offset", "900"]):
        assert main(["synth", str(tmp_path / "c.mcap"), *bad, "-q"]) == 2
        err = capsys.readouterr().err
        assert len(err.strip().splitlines()) == 1, err
    assert not (tmp_path / "c.mcap").exists()

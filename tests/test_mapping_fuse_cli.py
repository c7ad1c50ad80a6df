"""`slam fuse` on real RGB-D data: writes a PLY that reads back; user errors are one line."""

from __future__ import annotations

import numpy as np
from conftest import require

from datasets.ply import read_ply
from tools.cli import main


def test_fuse_seven_scenes_writes_a_readable_mesh(shared_data, tmp_path, capsys, monkeypatch):
    import datasets.rgbd_calibration as rc

    folder = require(shared_data / "7scenes_rgbd_400")
    # The colour calibration (minutes, cached per folder) is tested on its own; here it is fast.
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))
    monkeypatch.setattr(rc, "calibrate_color_camera", lambda *a, **k: _kinect_colour_camera())
    out = tmp_path / "kitchen.ply"
    pts = tmp_path / "points.ply"
    rc = main(
        [
            "fuse",
            str(folder),
            "--out",
            str(out),
            "--voxel",
            "0.05",
            "--every",
            "40",
            "--points",
            str(pts),
        ]
    )
    assert rc == 0
    ply = read_ply(out)
    n_v = int(ply.header.split("element vertex ")[1].split()[0])
    n_f = int(ply.header.split("element face ")[1].split()[0])
    assert n_v == len(ply.points) > 1000 and n_f == len(ply.faces) > 1000
    assert {"nx", "red"} <= set(ply.vertex)
    assert ply.faces.max() < n_v
    extent = ply.points.max(axis=0) - ply.points.min(axis=0)
    assert np.all(extent > 1.0) and np.all(extent < 8.0)
    assert len(read_ply(pts).points) > 1000
    out_text = capsys.readouterr().out
    assert "vertices" in out_text and "colour registered, mesh colour error" in out_text
    assert len(list((tmp_path / "cache" / "pyvislam" / "rgbd_calibration").glob("*.json"))) == 1


def test_fuse_reports_a_missing_input_in_one_line(tmp_path, capsys):
    rc = main(["fuse", str(tmp_path / "nope"), "--out", str(tmp_path / "m.ply")])
    assert rc == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "slam fuse: error:" in err[0]


def _kinect_colour_camera():
    """The 7-Scenes colour camera as the focal-only calibration finds it (522-529 px)."""
    from datasets.rgbd_calibration import ColorCalibration
    from slam.core.calibration import CameraIntrinsics

    return ColorCalibration(CameraIntrinsics(640, 480, 525.0, 525.0, 319.5, 239.5), np.eye(4))


def test_registered_colour_lowers_the_mesh_colour_error(shared_data):
    """Fusing the colour image as if the depth camera (585 px) took it smears colours across
    edges; registered to the depth first, the mesh's colours match the registered images."""
    from mapping.fuse import fuse_rgbd_folder
    from mapping.mapper import MapperConfig
    from mapping.tsdf import TsdfConfig

    folder = require(shared_data / "7scenes_rgbd_400")
    cfg = MapperConfig(
        tsdf=TsdfConfig(voxel_m=0.03, max_depth_m=4.0),
        mesh_min_weight=0.0,
        min_motion_m=0.0,
        min_motion_deg=0.0,
    )
    errors = {}
    for register in (False, True):
        res = fuse_rgbd_folder(
            folder,
            cfg,
            every=20,
            progress=False,
            register_color=register,
            color_error_frames=6,
            color_calibration=_kinect_colour_camera(),
        )
        assert res.color_registered == register and res.color_error is not None
        errors[register] = res.color_error
        assert np.mean(np.all(res.mesh.colors_rgb < 8, axis=1)) < 0.02  # no black mesh
    assert errors[True] < 0.8 * errors[False], errors


def test_colour_calibration_is_computed_once_per_folder(shared_data, tmp_path, monkeypatch):
    import datasets.rgbd_calibration as rc
    from datasets.rgbd_folder import RgbdFolder
    from mapping.fuse import color_registration

    folder = RgbdFolder(require(shared_data / "7scenes_rgbd_400"))
    calls = []

    def fake(source, pairs, config=None, progress=False):
        calls.append(len(pairs))
        return _kinect_colour_camera()

    monkeypatch.setattr(rc, "calibrate_color_camera", fake)
    first = color_registration(folder, tmp_path, progress=False)
    again = color_registration(folder, tmp_path, progress=False)
    assert len(calls) == 1 and calls[0] >= 10
    assert again.intrinsics.fx == first.intrinsics.fx == 525.0
    np.testing.assert_array_equal(again.color_from_depth, np.eye(4))
    assert len(list(tmp_path.glob("*.json"))) == 1

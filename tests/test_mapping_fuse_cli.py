"""`slam fuse` on real RGB-D data: writes a PLY that reads back; user errors are one line."""

from __future__ import annotations

import numpy as np
from conftest import require

from datasets.ply import read_ply
from tools.cli import main


def test_fuse_seven_scenes_writes_a_readable_mesh(shared_data, tmp_path, capsys):
    folder = require(shared_data / "7scenes_rgbd_400")
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
    assert "vertices" in capsys.readouterr().out


def test_fuse_reports_a_missing_input_in_one_line(tmp_path, capsys):
    rc = main(["fuse", str(tmp_path / "nope"), "--out", str(tmp_path / "m.ply")])
    assert rc == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "slam fuse: error:" in err[0]

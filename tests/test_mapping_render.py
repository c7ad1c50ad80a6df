"""The preview renderer's back-face culling, and bench_live_mesh's Markdown table."""

from __future__ import annotations

import numpy as np

from mapping.mesh import TriangleMesh
from mapping.render import look_at, render_mesh
from tools.bench_live_mesh import markdown_table


def _square(normal_z: float) -> TriangleMesh:
    """A 1 m square in the z = 2 plane, normals along +-z."""
    v = np.array([[-0.5, -0.5, 2.0], [0.5, -0.5, 2.0], [0.5, 0.5, 2.0], [-0.5, 0.5, 2.0]])
    f = np.array([[0, 1, 2], [0, 2, 3]], np.int32)
    n = np.tile([0.0, 0.0, normal_z], (4, 1)).astype(np.float32)
    return TriangleMesh(v.astype(np.float32), f, n, np.full((4, 3), 100, np.uint8))


def test_back_faces_are_culled_only_when_asked():
    cam = look_at(np.zeros(3), np.array([0.0, 0.0, 2.0]), np.array([0.0, -1.0, 0.0]))
    k = np.array([[100.0, 0.0, 80.0], [0.0, 100.0, 60.0], [0.0, 0.0, 1.0]])
    drawn = {}
    for name, nz in (("facing", -1.0), ("away", 1.0)):
        for cull in (False, True):
            img = render_mesh(_square(nz), cam, k, (160, 120), cull_back_faces=cull)
            drawn[name, cull] = int(np.sum(np.any(img != 255, axis=2)))
    # Splats of its two faces' samples (a point-splat renderer); culled only when the normals
    # point away from the camera.
    assert drawn["facing", False] > 10 and drawn["facing", True] == drawn["facing", False]
    assert drawn["away", False] == drawn["facing", False]
    assert drawn["away", True] == 0


def test_markdown_table_rows_and_missing_figures():
    results = {
        "speed": "1",
        "seq-a": {
            "keyframes_received": 120,
            "dropped_fraction": 0.05,
            "fused": 100,
            "depth_ms_p50": 80.4,
            "mapper_cpu_ms_p50": 101.2,
            "accuracy_mean_m": 0.0123,
            "completion_5cm": 0.931,
            "black_fraction": 0.0021,
            "frontend_p99_ms_with_mesh": 21.6,
            "frontend_p99_ms_without_mesh": 19.2,
        },
    }
    lines = markdown_table(results).splitlines()
    assert len(lines) == 3  # header, rule, one sequence ("speed" is not a row)
    cells = [c.strip() for c in lines[2].strip("|").split("|")]
    head = [c.strip() for c in lines[0].strip("|").split("|")]
    row = dict(zip(head, cells))
    assert row["sequence"] == "seq-a" and row["dropped"] == "5.0%"
    assert row["fusion ms p50"] == "-"  # missing
    assert row["accuracy cm"] == "1.23" and row["completion 5 cm"] == "93.1%"
    assert row["mapper CPU ms/kf p50"] == "101" and row["FE p99 ms mesh / none"] == "22 / 19"

"""Pose graphs: g2o round trip, convergence on benchmark graphs, robustness to a false loop."""

from __future__ import annotations

from pathlib import Path

import gtsam
import numpy as np
import pytest
from conftest import require
from scipy.spatial.transform import Rotation

from slam.core.errors import InputError
from slam.core.geometry import invert_transform, so3_exp
from slam.posegraph import (
    PgoOptions,
    PoseEdge,
    PoseGraph,
    information_from_sigmas,
    optimize,
    optimize_pose_graph,
    read_g2o,
    write_g2o,
)
from tools.cli import main as slam_main


def _assert_graphs_equal(a: PoseGraph, b: PoseGraph) -> None:
    for name in (
        "node_ids",
        "positions_m",
        "q_wxyz",
        "edge_ids",
        "edge_t_m",
        "edge_q_wxyz",
        "edge_information",
        "edge_is_loop",
    ):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name), err_msg=name)


def test_g2o_round_trip_is_bit_exact(shared_data: Path, tmp_path: Path) -> None:
    src = require(shared_data / "posegraphs" / "parking-garage.g2o")
    graph = read_g2o(src)
    assert (graph.num_nodes, graph.num_edges) == (1661, 6275)
    write_g2o(graph, tmp_path / "a.g2o")
    _assert_graphs_equal(graph, read_g2o(tmp_path / "a.g2o"))
    # Values computed here (not parsed from short decimal strings) survive too.
    opt = optimize(graph, PgoOptions(robust="none")).graph
    write_g2o(opt, tmp_path / "b.g2o")
    _assert_graphs_equal(opt, read_g2o(tmp_path / "b.g2o"))


def test_read_g2o_errors(tmp_path: Path) -> None:
    with pytest.raises(InputError, match="no such"):
        read_g2o(tmp_path / "missing.g2o")
    bad = tmp_path / "bad.g2o"
    bad.write_text("VERTEX_SE2 0 0 0 0\nEDGE_SE2 0 1 1 0 0 1 0 0 1 0 1\n")
    with pytest.raises(InputError, match="2-D"):
        read_g2o(bad)
    bad.write_text("VERTEX_SE3:QUAT 0 0 0 0 0 0 0 1\nEDGE_SE3:QUAT 0 1 1 0 0 0 0 0 1 1 0\n")
    with pytest.raises(InputError, match=":2:"):
        read_g2o(bad)


def _gtsam_reference_chi2(path: Path) -> tuple[float, float]:
    """(initial, optimised) chi2 with GTSAM's own reader, chordal init and LM."""
    graph, initial = gtsam.readG2o(str(path), True)
    graph.add(gtsam.PriorFactorPose3(0, initial.atPose3(0), gtsam.noiseModel.Constrained.All(6)))
    start = gtsam.InitializePose3.initialize(graph)
    result = gtsam.LevenbergMarquardtOptimizer(graph, start).optimize()
    return 2.0 * graph.error(initial), 2.0 * graph.error(result)


def test_slam_pgo_parking_garage_converges(
    shared_data: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    src = require(shared_data / "posegraphs" / "parking-garage.g2o")
    out = tmp_path / "opt.g2o"
    assert slam_main(["pgo", str(src), "--out", str(out)]) == 0
    text = capsys.readouterr().out
    initial = float(text.split("initial chi2")[1].split()[0])
    final = float(text.split("final chi2")[1].split()[0])
    ref_initial, ref_final = _gtsam_reference_chi2(src)
    assert initial == pytest.approx(ref_initial, rel=1e-6)
    assert final < 1e-3 * initial
    assert final == pytest.approx(ref_final, rel=1e-4)
    # The written graph is at the optimum: re-optimising from it changes nothing.
    again = optimize(read_g2o(out), PgoOptions(robust="none", chordal_init=False))
    assert again.initial_chi2 == pytest.approx(final, rel=1e-9)
    assert again.final_chi2 == pytest.approx(final, rel=1e-6)


def _sphere_ground_truth(path: Path) -> dict[int, np.ndarray]:
    """Poses from the noise-free EDGE3 file (x y z roll pitch yaw) chained along odometry."""
    edges: dict[tuple[int, int], np.ndarray] = {}
    for line in path.read_text().splitlines():
        parts = line.split()
        if not parts or parts[0] != "EDGE3":
            continue
        v = [float(x) for x in parts[3:9]]
        t = np.eye(4)
        t[:3, :3] = Rotation.from_euler("ZYX", [v[5], v[4], v[3]]).as_matrix()  # yaw, pitch, roll
        t[:3, 3] = v[:3]
        edges[(int(parts[1]), int(parts[2]))] = t
    poses = {0: np.eye(4)}
    k = 0
    while (k, k + 1) in edges:
        poses[k + 1] = poses[k] @ edges[(k, k + 1)]
        k += 1
    # The chained poses agree with every loop edge of the ground truth (checks the convention).
    worst = max(
        np.abs(invert_transform(poses[i]) @ poses[j] - t).max() for (i, j), t in edges.items()
    )
    assert worst < 1e-3
    return poses


def _aligned_ate_m(est: np.ndarray, gt: np.ndarray) -> float:
    """RMS position error after the best rigid alignment (Umeyama without scale)."""
    mu_e, mu_g = est.mean(0), gt.mean(0)
    u, _, vt = np.linalg.svd((est - mu_e).T @ (gt - mu_g))
    d = np.diag([1.0, 1.0, np.sign(np.linalg.det(vt.T @ u.T))])
    rot = vt.T @ d @ u.T
    aligned = (est - mu_e) @ rot.T + mu_g
    return float(np.sqrt(np.mean(np.sum((aligned - gt) ** 2, axis=1))))


def test_slam_pgo_sphere2500_matches_ground_truth(
    shared_data: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    src = require(shared_data / "posegraphs" / "sphere2500.g2o")
    gt_file = require(shared_data / "posegraphs" / "sphere2500_groundtruth.txt")
    out = tmp_path / "opt.g2o"
    assert slam_main(["pgo", str(src), "--out", str(out), "--robust", "huber"]) == 0
    text = capsys.readouterr().out
    initial = float(text.split("initial chi2")[1].split()[0])
    final = float(text.split("final chi2")[1].split()[0])
    assert final < 1e-3 * initial
    gt = _sphere_ground_truth(gt_file)
    noisy, opt = read_g2o(src), read_g2o(out)
    gt_xyz = np.array([gt[int(i)][:3, 3] for i in opt.node_ids])
    ate_before = _aligned_ate_m(noisy.positions_m, gt_xyz)
    ate_after = _aligned_ate_m(opt.positions_m, gt_xyz)
    # Sphere radius 50 m; measured: 27.9 m before, 0.18 m after.
    assert ate_after < 0.5
    assert ate_after < 0.02 * ate_before


def _two_lap_circle(seed: int = 0) -> tuple[dict, list[PoseEdge], list[PoseEdge], dict]:
    """Two laps of a 10 m circle (rising 2 cm per node): drifting odometry and true loops."""
    rng = np.random.default_rng(seed)
    n_lap = 100
    gt: dict[int, np.ndarray] = {}
    for k in range(2 * n_lap):
        a = 2 * np.pi * k / n_lap
        t = np.eye(4)
        t[:3, :3] = so3_exp(np.array([0.0, 0.0, a + np.pi / 2]))
        t[:3, 3] = [10 * np.cos(a), 10 * np.sin(a), 0.02 * k]
        gt[k] = t

    def noisy(t: np.ndarray, s_m: float, s_rad: float) -> np.ndarray:
        n = np.eye(4)
        n[:3, :3] = so3_exp(rng.normal(0, s_rad, 3))
        n[:3, 3] = rng.normal(0, s_m, 3)
        return t @ n

    rel = lambda i, j: invert_transform(gt[i]) @ gt[j]  # noqa: E731
    odo = [
        PoseEdge(k, k + 1, noisy(rel(k, k + 1), 0.02, 0.003), information_from_sigmas(0.02, 0.003))
        for k in range(2 * n_lap - 1)
    ]
    loops = [
        PoseEdge(
            k, k + n_lap, noisy(rel(k, k + n_lap), 0.05, 0.01), information_from_sigmas(0.05, 0.01)
        )
        for k in range(0, n_lap, 10)
    ]
    initial = {0: gt[0]}
    for e in odo:
        initial[e.to_id] = initial[e.from_id] @ e.from_node_from_to_node
    return initial, odo, loops, gt


def _ate(poses: dict[int, np.ndarray], gt: dict[int, np.ndarray]) -> float:
    return float(np.sqrt(np.mean([np.sum((poses[k][:3, 3] - gt[k][:3, 3]) ** 2) for k in gt])))


@pytest.mark.parametrize("robust", ["huber", "cauchy", "gnc"])
def test_false_loop_is_rejected_or_down_weighted(robust: str) -> None:
    initial, odo, loops, gt = _two_lap_circle()
    # A false loop: node 25 and node 175 are on opposite sides of the circle (20 m apart).
    false_loop = PoseEdge(25, 175, np.eye(4), information_from_sigmas(0.05, 0.01))
    odometry_ate = _ate(initial, gt)
    good = _ate(optimize_pose_graph(initial, odo, loops, robust=robust), gt)
    plain_bad = _ate(optimize_pose_graph(initial, odo, [*loops, false_loop], robust="none"), gt)
    robust_bad = _ate(optimize_pose_graph(initial, odo, [*loops, false_loop], robust=robust), gt)
    assert good < 0.7 * odometry_ate  # the true loops help
    assert plain_bad > 5 * odometry_ate  # the false loop wrecks plain least squares ...
    assert robust_bad < good + 0.03  # ... but not the robust optimisation
    result = optimize(
        PoseGraph.from_poses(initial, odo, [*loops, false_loop]), PgoOptions(robust=robust)
    )
    assert not result.loop_inliers[-1]
    assert result.loop_weights[-1] < 0.01
    assert result.inlier_chi2 < 1e-3 * result.final_chi2


def test_optimize_pose_graph_keeps_fixed_node_and_ids() -> None:
    initial, odo, loops, _ = _two_lap_circle(seed=1)
    out = optimize_pose_graph(initial, odo, loops, robust="none", fixed_id=0)
    assert sorted(out) == sorted(initial)
    np.testing.assert_allclose(out[0], initial[0], atol=1e-9)

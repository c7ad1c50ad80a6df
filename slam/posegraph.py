"""3-D pose graphs: g2o file I/O (full float precision) and optimisation with GTSAM.

Conventions
-----------
* A node's pose is ``world_from_node`` (g2o ``VERTEX_SE3:QUAT id x y z qx qy qz qw``).
* An edge ``i -> j`` measures ``node_i_from_node_j = inv(world_from_i) @ world_from_j``
  (g2o ``EDGE_SE3:QUAT i j x y z qx qy qz qw`` followed by the 21 upper-triangular entries of the
  6x6 information matrix, row by row, in g2o's order: translation x y z, then rotation).
* GTSAM orders the Pose3 tangent rotation first, so the information matrix is permuted when the
  graph is handed to GTSAM (as ``gtsam.readG2o`` does).

Why not ``gtsam.readG2o``/``writeG2o``: ``writeG2o`` prints 6 significant digits (the optimum's
cost moves after a round trip) and refuses robust noise models. Here values are written with
``repr`` (shortest round-trip form), so write -> read is bit-exact.

Optimisation: chordal initialisation (``gtsam.InitializePose3``) then Levenberg-Marquardt; loop
edges may carry a robust kernel (Huber, Cauchy) or go through graduated non-convexity
(``gtsam.GncLMOptimizer`` with a truncated-quadratic loss, odometry edges known inliers), so a
false loop is down-weighted or rejected. Costs are reported as chi2 = sum r^T Info r under the
plain Gaussian model, whatever kernel was used to optimise.

GTSAM holds the GIL for a whole solve: call :func:`optimize_pose_graph` from a worker process.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

import gtsam
import numpy as np
from scipy.special import gammaincinv

from slam.core.atomic import write_atomic
from slam.core.errors import InputError
from slam.core.geometry import matrix_to_quat_wxyz, quat_wxyz_to_matrix

log = logging.getLogger(__name__)

RobustKind = Literal["none", "huber", "cauchy", "gnc"]
ROBUST_KINDS: tuple[str, ...] = ("none", "huber", "cauchy", "gnc")

# g2o orders the tangent (tx, ty, tz, rx, ry, rz); GTSAM's Pose3 orders (rx, ry, rz, tx, ty, tz).
_G2O_TO_GTSAM = np.array([3, 4, 5, 0, 1, 2])
_TRIU = np.triu_indices(6)
# 16.8: inlier chi2 bound of one 6-dof edge (the chi2 quantile 2 P^-1(k/2, p); scipy.stats
# costs 1.3 s of every run's start-up)
_GNC_CHI2 = float(2.0 * gammaincinv(3.0, 0.99))
GNC_INLIER_CHI2 = _GNC_CHI2
DEFAULT_KERNEL_WIDTH = {"huber": 1.345, "cauchy": 1.0}


@dataclass(frozen=True, eq=False)
class PoseEdge:
    """One relative-pose measurement between two nodes (picklable, for worker processes).

    ``from_node_from_to_node`` is the 4x4 pose of node ``to_id`` in node ``from_id``'s frame.
    ``information`` is 6x6 in g2o order (translation first, then rotation; 1/m^2, 1/rad^2).
    """

    from_id: int
    to_id: int
    from_node_from_to_node: np.ndarray
    information: np.ndarray


@dataclass(eq=False)
class PoseGraph:
    """Nodes and edges as arrays, keeping the exact values read from a file.

    ``node_ids`` (N,) int64; ``positions_m`` (N, 3) and ``q_wxyz`` (N, 4): world_from_node.
    Edges: ``edge_ids`` (M, 2) int64 (from, to); ``edge_t_m`` (M, 3), ``edge_q_wxyz`` (M, 4):
    from_node_from_to_node; ``edge_information`` (M, 6, 6) in g2o order; ``edge_is_loop`` (M,)
    bool: edges that get the robust treatment (default: any edge that does not join
    consecutive ids).
    """

    node_ids: np.ndarray
    positions_m: np.ndarray
    q_wxyz: np.ndarray
    edge_ids: np.ndarray
    edge_t_m: np.ndarray
    edge_q_wxyz: np.ndarray
    edge_information: np.ndarray
    edge_is_loop: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=bool))

    def __post_init__(self) -> None:
        if len(self.edge_is_loop) != len(self.edge_ids):
            self.edge_is_loop = np.abs(self.edge_ids[:, 1] - self.edge_ids[:, 0]) != 1

    @property
    def num_nodes(self) -> int:
        return len(self.node_ids)

    @property
    def num_edges(self) -> int:
        return len(self.edge_ids)

    def world_from_node(self) -> dict[int, np.ndarray]:
        """Node poses as {id: 4x4 world_from_node}."""
        rot = quat_wxyz_to_matrix(self.q_wxyz) if self.num_nodes else np.zeros((0, 3, 3))
        out: dict[int, np.ndarray] = {}
        for k, node_id in enumerate(self.node_ids):
            t = np.eye(4)
            t[:3, :3] = rot[k]
            t[:3, 3] = self.positions_m[k]
            out[int(node_id)] = t
        return out

    def edges(self) -> list[PoseEdge]:
        """Edges as :class:`PoseEdge` objects."""
        rot = quat_wxyz_to_matrix(self.edge_q_wxyz) if self.num_edges else np.zeros((0, 3, 3))
        out = []
        for k in range(self.num_edges):
            t = np.eye(4)
            t[:3, :3] = rot[k]
            t[:3, 3] = self.edge_t_m[k]
            out.append(
                PoseEdge(
                    int(self.edge_ids[k, 0]),
                    int(self.edge_ids[k, 1]),
                    t,
                    self.edge_information[k].copy(),
                )
            )
        return out

    @staticmethod
    def from_poses(
        world_from_node: dict[int, np.ndarray],
        odometry_edges: Sequence[PoseEdge],
        loop_edges: Sequence[PoseEdge] = (),
    ) -> PoseGraph:
        """Build a graph from 4x4 poses and edges; ``loop_edges`` get the robust treatment."""
        ids = np.array(sorted(world_from_node), dtype=np.int64)
        mats = np.array([world_from_node[int(i)] for i in ids]).reshape(-1, 4, 4)
        edges = list(odometry_edges) + list(loop_edges)
        emats = np.array([e.from_node_from_to_node for e in edges]).reshape(-1, 4, 4)
        return PoseGraph(
            node_ids=ids,
            positions_m=mats[:, :3, 3].copy(),
            q_wxyz=matrix_to_quat_wxyz(mats[:, :3, :3]) if len(ids) else np.zeros((0, 4)),
            edge_ids=np.array([(e.from_id, e.to_id) for e in edges], dtype=np.int64).reshape(-1, 2),
            edge_t_m=emats[:, :3, 3].copy(),
            edge_q_wxyz=matrix_to_quat_wxyz(emats[:, :3, :3]) if edges else np.zeros((0, 4)),
            edge_information=np.array([e.information for e in edges], dtype=float).reshape(
                -1, 6, 6
            ),
            edge_is_loop=np.array(
                [False] * len(odometry_edges) + [True] * len(loop_edges), dtype=bool
            ),
        )


# --------------------------------------------------------------------------------------------
# g2o I/O
# --------------------------------------------------------------------------------------------


def read_g2o(path: str | Path) -> PoseGraph:
    """Read a 3-D g2o pose graph (``VERTEX_SE3:QUAT``, ``EDGE_SE3:QUAT``).

    Other tags (``FIX``, comments) are skipped; 2-D tags raise :class:`InputError`.
    """
    path = Path(path)
    if not path.is_file():
        raise InputError(f"{path}: no such g2o file")
    node_ids: list[int] = []
    node_vals: list[list[float]] = []
    edge_ids: list[tuple[int, int]] = []
    edge_vals: list[list[float]] = []
    with path.open() as f:
        for line_no, line in enumerate(f, start=1):
            parts = line.split()
            if not parts or parts[0].startswith("#"):
                continue
            tag = parts[0]
            try:
                if tag == "VERTEX_SE3:QUAT":
                    node_ids.append(int(parts[1]))
                    node_vals.append([float(x) for x in parts[2:9]])
                    if len(node_vals[-1]) != 7:
                        raise ValueError("expected 7 numbers")
                elif tag == "EDGE_SE3:QUAT":
                    edge_ids.append((int(parts[1]), int(parts[2])))
                    edge_vals.append([float(x) for x in parts[3:31]])
                    if len(edge_vals[-1]) != 28:
                        raise ValueError("expected 7 pose numbers + 21 information entries")
                elif tag in ("VERTEX_SE2", "EDGE_SE2", "VERTEX2", "EDGE2"):
                    raise InputError(
                        f"{path}:{line_no}: 2-D tag {tag}; only 3-D graphs "
                        "(VERTEX_SE3:QUAT / EDGE_SE3:QUAT) are supported"
                    )
            except (ValueError, IndexError) as exc:
                raise InputError(f"{path}:{line_no}: cannot parse {tag} line ({exc})") from exc
    if not edge_ids:
        raise InputError(f"{path}: no EDGE_SE3:QUAT lines: not a 3-D g2o pose graph")
    nv = np.array(node_vals, dtype=float).reshape(-1, 7)
    ev = np.array(edge_vals, dtype=float).reshape(-1, 28)
    info = np.zeros((len(ev), 6, 6))
    info[:, _TRIU[0], _TRIU[1]] = ev[:, 7:]
    info = info + np.triu(info, 1).transpose(0, 2, 1)
    eids = np.array(edge_ids, dtype=np.int64).reshape(-1, 2)
    graph = PoseGraph(
        node_ids=np.array(node_ids, dtype=np.int64),
        positions_m=nv[:, :3].copy(),
        q_wxyz=nv[:, [6, 3, 4, 5]].copy(),  # g2o stores qx qy qz qw
        edge_ids=eids,
        edge_t_m=ev[:, :3].copy(),
        edge_q_wxyz=ev[:, [6, 3, 4, 5]].copy(),  # g2o stores qx qy qz qw
        edge_information=info,
    )
    missing = set(np.unique(eids).tolist()) - set(graph.node_ids.tolist())
    if missing:
        raise InputError(
            f"{path}: edges refer to {len(missing)} node(s) without a VERTEX_SE3:QUAT line "
            f"(e.g. {min(missing)})"
        )
    return graph


def _fmt(values: Iterable[float]) -> str:
    return " ".join(repr(float(v)) for v in values)


def write_g2o(graph: PoseGraph, path: str | Path) -> None:
    """Write ``graph`` as g2o text with every float at full precision (atomically)."""
    path = Path(path)
    lines: list[str] = []
    for k, node_id in enumerate(graph.node_ids):
        q = graph.q_wxyz[k]
        lines.append(
            f"VERTEX_SE3:QUAT {int(node_id)} "
            + _fmt([*graph.positions_m[k], q[1], q[2], q[3], q[0]])  # g2o: qx qy qz qw
        )
    for k in range(graph.num_edges):
        q = graph.edge_q_wxyz[k]
        info = graph.edge_information[k][_TRIU]
        lines.append(
            f"EDGE_SE3:QUAT {int(graph.edge_ids[k, 0])} {int(graph.edge_ids[k, 1])} "
            + _fmt([*graph.edge_t_m[k], q[1], q[2], q[3], q[0]])  # g2o: qx qy qz qw
            + " "
            + _fmt(info)
        )
    _atomic_write_text(path, "\n".join(lines) + "\n")


def _atomic_write_text(path: Path, text: str) -> None:
    write_atomic(path, text)


# --------------------------------------------------------------------------------------------
# Optimisation
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class PgoOptions:
    """How to optimise a pose graph."""

    robust: RobustKind = "cauchy"
    """Treatment of loop edges: none (plain least squares), huber, cauchy, or gnc (graduated
    non-convexity with a truncated quadratic: outlier loops end with weight 0)."""
    robust_threshold: float = 0.0
    """Kernel width in whitened units (sigmas); 0 = default (Huber 1.345, Cauchy 1.0). For GNC,
    the inlier chi2 threshold of one edge; 0 = the 99% chi2 quantile for 6 dof."""
    chordal_init: bool = True
    """Start from chordal rotation initialisation (InitializePose3) rather than the given poses."""
    max_iterations: int = 100
    relative_error_tol: float = 1e-5
    fixed_id: int | None = None
    """Node held at its given pose (gauge); default the smallest id."""


@dataclass(eq=False)
class PgoResult:
    """What an optimisation did. chi2 values are under the plain Gaussian model (no kernel)."""

    graph: PoseGraph
    initial_chi2: float
    """chi2 of the given poses."""
    start_chi2: float
    """chi2 after initialisation (equals initial_chi2 without chordal init)."""
    final_chi2: float
    iterations: int
    seconds: float
    loop_weights: np.ndarray
    """(num loop edges,) in [0, 1]: GNC weights, or the robust kernel's weight at the optimum
    (1 for none)."""
    loop_edge_indices: np.ndarray
    """Indices into graph edges of the loop edges (same order as ``loop_weights``)."""
    loop_chi2: np.ndarray
    """(num loop edges,) chi2 of each loop edge at the optimum."""
    loop_inliers: np.ndarray
    """(num loop edges,) bool: GNC weight >= 0.5, or (other kinds) chi2 within the inlier
    threshold (99% quantile of chi2 with 6 dof, 16.8)."""
    inlier_chi2: float
    """chi2 over odometry edges and inlier loop edges."""

    @property
    def num_rejected_loops(self) -> int:
        return int(np.sum(~self.loop_inliers))


def _pose3(t: np.ndarray, q_wxyz: np.ndarray) -> gtsam.Pose3:
    return gtsam.Pose3(
        gtsam.Rot3.Quaternion(
            float(q_wxyz[0]), float(q_wxyz[1]), float(q_wxyz[2]), float(q_wxyz[3])
        ),
        np.asarray(t, dtype=float),
    )


def gaussian_from_g2o_information(info_g2o: np.ndarray) -> gtsam.noiseModel.Gaussian:
    """GTSAM noise model of a 6x6 information matrix in g2o's order (translation first;
    GTSAM's Pose3 tangent puts rotation first)."""
    info_gtsam = info_g2o[np.ix_(_G2O_TO_GTSAM, _G2O_TO_GTSAM)]
    return gtsam.noiseModel.Gaussian.Information(info_gtsam)


def _robust_model(
    kind: str, threshold: float, base: gtsam.noiseModel.Base
) -> gtsam.noiseModel.Base:
    est: gtsam.noiseModel.mEstimator.Base
    if kind == "huber":
        est = gtsam.noiseModel.mEstimator.Huber.Create(threshold or 1.345)
    elif kind == "cauchy":
        est = gtsam.noiseModel.mEstimator.Cauchy.Create(threshold or 1.0)
    else:
        raise ValueError(kind)
    return gtsam.noiseModel.Robust.Create(est, base)


def _values(graph: PoseGraph) -> gtsam.Values:
    values = gtsam.Values()
    for k, node_id in enumerate(graph.node_ids):
        values.insert(int(node_id), _pose3(graph.positions_m[k], graph.q_wxyz[k]))
    return values


def _edge_factors(
    graph: PoseGraph, robust: str, threshold: float
) -> tuple[list[gtsam.BetweenFactorPose3], list[gtsam.BetweenFactorPose3]]:
    """(plain factors, factors with the kernel on loop edges), one per edge, same order."""
    plain, kernel = [], []
    for k in range(graph.num_edges):
        i, j = int(graph.edge_ids[k, 0]), int(graph.edge_ids[k, 1])
        meas = _pose3(graph.edge_t_m[k], graph.edge_q_wxyz[k])
        base = gaussian_from_g2o_information(graph.edge_information[k])
        plain.append(gtsam.BetweenFactorPose3(i, j, meas, base))
        if robust in ("huber", "cauchy") and graph.edge_is_loop[k]:
            kernel.append(
                gtsam.BetweenFactorPose3(i, j, meas, _robust_model(robust, threshold, base))
            )
        else:
            kernel.append(plain[-1])
    return plain, kernel


def _chi2(factors: Sequence[gtsam.NonlinearFactor], values: gtsam.Values) -> np.ndarray:
    """Per-factor chi2 (= 2 x GTSAM's Gaussian error)."""
    return np.array([2.0 * f.error(values) for f in factors])


def _graph_from(factors: Iterable[gtsam.NonlinearFactor]) -> gtsam.NonlinearFactorGraph:
    g = gtsam.NonlinearFactorGraph()
    for f in factors:
        g.add(f)
    return g


def optimize(graph: PoseGraph, options: PgoOptions | None = None) -> PgoResult:
    """Optimise a pose graph; returns the optimised copy and the costs.

    The node ``options.fixed_id`` (default: smallest id) keeps its given pose.
    """
    opts = options or PgoOptions()
    if opts.robust not in ROBUST_KINDS:
        raise InputError(f"unknown robust kind {opts.robust!r}; choose one of {ROBUST_KINDS}")
    if graph.num_nodes == 0:
        raise InputError("pose graph has no nodes")
    t0 = time.perf_counter()
    values0 = _values(graph)
    fixed_id = int(graph.node_ids.min()) if opts.fixed_id is None else int(opts.fixed_id)
    if not values0.exists(fixed_id):
        raise InputError(f"fixed node {fixed_id} is not in the graph")
    fixed_pose = values0.atPose3(fixed_id)
    prior = gtsam.PriorFactorPose3(fixed_id, fixed_pose, gtsam.noiseModel.Constrained.All(6))

    plain, kernel = _edge_factors(graph, opts.robust, opts.robust_threshold)
    initial_chi2 = float(_chi2(plain, values0).sum())

    if opts.chordal_init:
        init_graph = _graph_from([prior, *plain])
        try:
            start = gtsam.InitializePose3.initialize(init_graph)
        except RuntimeError as exc:
            log.warning("chordal initialisation failed (%s); starting from the given poses", exc)
            start = values0
        else:
            # Chordal init may move the gauge: put the fixed node back on its given pose.
            correction = fixed_pose.compose(start.atPose3(fixed_id).inverse())
            moved = gtsam.Values()
            for key in start.keys():
                moved.insert(key, correction.compose(start.atPose3(key)))
            start = moved
    else:
        start = values0
    start_chi2 = float(_chi2(plain, start).sum())

    loop_idx = np.flatnonzero(graph.edge_is_loop)
    if opts.robust == "gnc":
        full = _graph_from([prior, *plain])
        lm_params = gtsam.LevenbergMarquardtParams()
        lm_params.setMaxIterations(opts.max_iterations)
        lm_params.setRelativeErrorTol(opts.relative_error_tol)
        params = gtsam.GncLMParams(lm_params)
        # Factor 0 is the prior; odometry edges are known inliers, loop edges are tested.
        known = [0] + [int(k) + 1 for k in np.flatnonzero(~graph.edge_is_loop)]
        params.setKnownInliers(known)
        gnc = gtsam.GncLMOptimizer(full, start, params)
        # GTSAM thresholds the factor error (= chi2 / 2).
        thr_chi2 = opts.robust_threshold or _GNC_CHI2
        gnc.setInlierCostThresholds(thr_chi2 / 2.0)
        result = gnc.optimize()
        weights = np.asarray(gnc.getWeights(), dtype=float)
        loop_weights = weights[loop_idx + 1] if len(loop_idx) else np.zeros(0)
        iterations = -1  # GncLMOptimizer does not expose its iteration count
        # Polish on the inlier set with plain LM (reports iterations; a no-op when converged).
        keep = [prior] + [plain[k] for k in range(graph.num_edges) if weights[k + 1] >= 0.5]
        lm = gtsam.LevenbergMarquardtOptimizer(_graph_from(keep), result, lm_params)
        result = lm.optimize()
        iterations = int(lm.iterations())
    else:
        lm_params = gtsam.LevenbergMarquardtParams()
        lm_params.setMaxIterations(opts.max_iterations)
        lm_params.setRelativeErrorTol(opts.relative_error_tol)
        lm = gtsam.LevenbergMarquardtOptimizer(_graph_from([prior, *kernel]), start, lm_params)
        result = lm.optimize()
        iterations = int(lm.iterations())
        if opts.robust == "none" or not len(loop_idx):
            loop_weights = np.ones(len(loop_idx))
        else:
            loop_weights = np.array(
                [_kernel_weight(kernel[k], plain[k], result) for k in loop_idx], dtype=float
            )

    per_edge = _chi2(plain, result)
    loop_chi2 = per_edge[loop_idx]
    if opts.robust == "gnc":
        loop_inliers = loop_weights >= 0.5
    else:
        loop_inliers = loop_chi2 <= _GNC_CHI2
    inlier_mask = ~graph.edge_is_loop.copy()
    inlier_mask[loop_idx[loop_inliers]] = True
    out = _graph_with_values(graph, result)
    return PgoResult(
        graph=out,
        initial_chi2=initial_chi2,
        start_chi2=start_chi2,
        final_chi2=float(per_edge.sum()),
        iterations=iterations,
        seconds=time.perf_counter() - t0,
        loop_weights=loop_weights,
        loop_edge_indices=loop_idx,
        loop_chi2=loop_chi2,
        loop_inliers=loop_inliers,
        inlier_chi2=float(per_edge[inlier_mask].sum()),
    )


def _kernel_weight(
    robust_factor: gtsam.BetweenFactorPose3,
    plain_factor: gtsam.BetweenFactorPose3,
    values: gtsam.Values,
) -> float:
    """The robust kernel's weight at ``values`` (1 = full, ->0 = ignored).

    The Mahalanobis distance comes from the plain factor: a robust factor's whitened error is
    already scaled by the kernel.
    """
    whitened = float(np.linalg.norm(plain_factor.whitenedError(values)))
    model: gtsam.noiseModel.Robust = robust_factor.noiseModel()  # type: ignore[assignment]
    return float(model.robust().weight(whitened))  # type: ignore[attr-defined]


def _graph_with_values(graph: PoseGraph, values: gtsam.Values) -> PoseGraph:
    n = graph.num_nodes
    positions = np.zeros((n, 3))
    rotations = np.zeros((n, 3, 3))
    for k, node_id in enumerate(graph.node_ids):
        pose = values.atPose3(int(node_id))
        positions[k] = pose.translation()
        rotations[k] = pose.rotation().matrix()
    return PoseGraph(
        node_ids=graph.node_ids.copy(),
        positions_m=positions,
        q_wxyz=matrix_to_quat_wxyz(rotations) if n else np.zeros((0, 4)),
        edge_ids=graph.edge_ids.copy(),
        edge_t_m=graph.edge_t_m.copy(),
        edge_q_wxyz=graph.edge_q_wxyz.copy(),
        edge_information=graph.edge_information.copy(),
        edge_is_loop=graph.edge_is_loop.copy(),
    )


def optimize_pose_graph(
    world_from_node: dict[int, np.ndarray],
    odometry_edges: Sequence[PoseEdge],
    loop_edges: Sequence[PoseEdge],
    robust: RobustKind = "cauchy",
    chordal_init: bool = True,
    fixed_id: int | None = None,
) -> dict[int, np.ndarray]:
    """Optimise keyframe poses {id: 4x4 world_from_node}; returns corrected poses, same ids.

    ``loop_edges`` get the robust treatment; the node ``fixed_id`` (default: smallest id) stays
    where it is. Picklable inputs and outputs: meant to run in a worker process.
    """
    graph = PoseGraph.from_poses(world_from_node, odometry_edges, loop_edges)
    result = optimize(
        graph, PgoOptions(robust=robust, chordal_init=chordal_init, fixed_id=fixed_id)
    )
    return result.graph.world_from_node()


def information_from_sigmas(sigma_m: float, sigma_rad: float) -> np.ndarray:
    """Diagonal 6x6 information in g2o order for isotropic translation/rotation sigmas."""
    return np.diag([sigma_m**-2] * 3 + [sigma_rad**-2] * 3)

"""`slam pgo`: optimise a g2o 3-D pose graph with GTSAM."""

from __future__ import annotations

import argparse
from pathlib import Path

DESCRIPTION = """\
Optimise a 3-D pose graph stored as g2o text (VERTEX_SE3:QUAT, EDGE_SE3:QUAT) and write the
result with full float precision.

Steps: chordal rotation initialisation (GTSAM InitializePose3), then Levenberg-Marquardt.
Edges that do not join consecutive ids are treated as loop closures; --robust puts a kernel
on them (huber, cauchy) or runs graduated non-convexity (gnc), so a false loop is
down-weighted or rejected. Costs are chi2 (sum of r^T Info r) under the plain Gaussian model.

Examples:
  slam pgo parking-garage.g2o --out garage_opt.g2o
  slam pgo sphere2500.g2o --out sphere_opt.g2o --robust cauchy
  slam pgo noisy.g2o --out opt.g2o --robust gnc --no-chordal-init
"""


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "pgo",
        help="optimise a g2o 3-D pose graph (GTSAM, robust loop edges)",
        description=DESCRIPTION,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("graph", type=Path, help="input .g2o file")
    p.add_argument("--out", type=Path, required=True, help="output .g2o file (optimised poses)")
    p.add_argument(
        "--robust",
        choices=["none", "huber", "cauchy", "gnc"],
        default="none",
        help="treatment of loop edges (default: none = plain least squares)",
    )
    p.add_argument(
        "--robust-threshold",
        type=float,
        default=0.0,
        help="kernel width in sigmas (huber/cauchy) or inlier chi2 per edge (gnc); 0 = default",
    )
    p.add_argument(
        "--no-chordal-init",
        action="store_true",
        help="start from the poses in the file instead of chordal initialisation",
    )
    p.add_argument("--max-iterations", type=int, default=100, help="LM iteration limit")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from slam.posegraph import PgoOptions, optimize, read_g2o, write_g2o

    graph = read_g2o(args.graph)
    result = optimize(
        graph,
        PgoOptions(
            robust=args.robust,
            robust_threshold=args.robust_threshold,
            chordal_init=not args.no_chordal_init,
            max_iterations=args.max_iterations,
        ),
    )
    write_g2o(result.graph, args.out)
    print(
        f"{args.graph.name}: {graph.num_nodes} nodes, {graph.num_edges} edges "
        f"({int(graph.edge_is_loop.sum())} loop)"
    )
    print(f"initial chi2      {result.initial_chi2:.10g}")
    if not args.no_chordal_init:
        print(f"after chordal     {result.start_chi2:.10g}")
    print(f"final chi2        {result.final_chi2:.10g}")
    print(f"iterations        {result.iterations}")
    if args.robust != "none":
        print(f"rejected loops    {result.num_rejected_loops} of {len(result.loop_inliers)}")
    print(f"time              {result.seconds:.2f} s")
    print(f"wrote {args.out}")
    return 0

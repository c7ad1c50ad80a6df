"""`slam eval`: score an estimated trajectory against ground truth (APE, RPE, tables).

Only argparse work happens at import time: the library (numpy) and matplotlib are imported
inside the handlers, so `slam eval` starts fast.
"""

from __future__ import annotations

import argparse
from typing import Any

FORMATS = ("tum", "euroc", "kitti", "bag", "run", "sequence")
ALIGNMENTS = ("se3", "sim3", "scale", "posyaw", "origin", "none")
RELATIONS = ("trans", "angle_deg", "angle_rad", "rot", "full")
TIME_UNITS = ("s", "ms", "us", "ns")

DESCRIPTION = """\
Score an estimated trajectory against a reference (ground truth), with the same numbers as evo.

  ape    absolute pose error after aligning the estimate to the reference
  rpe    relative pose error over deltas (frames, seconds or metres), or drift over
         sub-trajectory lengths (KITTI/rpg style, --lengths)
  table  gather result files (ours or evo's .zip) into one markdown/CSV/LaTeX table

INPUTS

Examples:
  slam eval ape gt.txt est.txt --align se3 --plot ape.png --json ape.json
  slam eval ape V1_01_easy/ run1/ --align posyaw          # VIO: 4-DoF alignment
  slam eval ape gt.csv mono.txt --align sim3 --interpolate
  slam eval rpe gt.txt est.txt --delta 1 10 --delta-unit metres --plot rpe.png
  slam eval rpe 00_gt.txt 00_est.txt --ref-times times.txt --lengths kitti
  slam eval table run1/ape.json run2/ape.json --format latex
"""

INPUTS = """\
Inputs (format detected, or forced with --format): TUM (.txt/.tum, seconds), EuRoC csv
(ground-truth or estimate layout, ns), KITTI (12 values per line, + optional times file),
ROS 1/2 bags and MCAP (PoseStamped, Odometry, ...: --ref-topic/--est-topic), a `slam run`
output folder, and a sequence (EuRoC folder, our MCAP) for its ground truth. Times in
another unit than the format's (EuRoC ns in a TUM file): --ref-time-unit/--est-time-unit."""
DESCRIPTION = DESCRIPTION.replace("INPUTS", INPUTS)

APE_DESCRIPTION = f"""\
Absolute pose error, as evo_ape: pair the estimate's poses with the reference's by time,
align the estimate (--align), then give the error of every pose (--relation) and its
statistics (rmse, mean, median, std, min, max).

{INPUTS}
"""
APE_EPILOG = """\
Examples:
  slam eval ape gt.txt est.txt --plot ape.png --json ape.json     # SE(3) alignment
  slam eval ape V1_01_easy/ run1/ --align posyaw                  # VIO: 4-DoF alignment
  slam eval ape gt.csv mono.txt --align sim3 --interpolate        # monocular: with scale
  slam eval ape gt.csv est.txt --est-time-unit ns                 # EuRoC ns in a TUM file
"""
RPE_DESCRIPTION = f"""\
Relative pose error, as evo_rpe: the error of the estimate's motion between poses a delta
apart (--delta in frames, seconds or metres). With --lengths instead: drift in % of the
length and deg/m over sub-trajectories of given lengths (KITTI/rpg style). Relative motion
needs no alignment (default none), except the scale of a monocular estimate (sim3, scale).

{INPUTS}
"""
RPE_EPILOG = """\
Examples:
  slam eval rpe gt.txt est.txt --delta 1 10 --plot rpe.png --json rpe.json
  slam eval rpe gt.txt est.txt --delta 1 --delta-unit metres --relation angle_deg
  slam eval rpe 00_gt.txt 00_est.txt --ref-times times.txt --lengths kitti --plot drift.png
"""
TABLE_DESCRIPTION = """\
One table of several results: the JSON files of `slam eval ape|rpe --json` (one result or a
list each) and evo's result zips (evo_ape/evo_rpe --save_results). A row per result: the run
(estimate), the metric (APE/RPE/drift, relation, unit, delta), the alignment, and the
statistics.
"""
TABLE_EPILOG = """\
Examples:
  slam eval table run1/ape.json run2/ape.json run1/rpe.json
  slam eval table run*/ape.json evo_results/*.zip --format latex --out table.tex
"""


def _common(p: argparse.ArgumentParser) -> None:
    p.add_argument("ref", help="reference (ground truth): file, folder or bag")
    p.add_argument("est", help="estimate: file, folder or bag")
    p.add_argument("--format", choices=FORMATS, help="force the format of both inputs")
    p.add_argument("--ref-format", choices=FORMATS, help="force the reference's format")
    p.add_argument("--est-format", choices=FORMATS, help="force the estimate's format")
    p.add_argument("--ref-topic", help="bag topic of the reference")
    p.add_argument("--est-topic", help="bag topic of the estimate")
    p.add_argument("--ref-times", help="KITTI: times file (s, one per line) of the reference")
    p.add_argument("--est-times", help="KITTI: times file of the estimate")
    p.add_argument(
        "--ref-time-unit",
        choices=TIME_UNITS,
        help="unit of the reference's time column (default: the format's, TUM s, EuRoC csv ns)",
    )
    p.add_argument(
        "--est-time-unit",
        choices=TIME_UNITS,
        help="unit of the estimate's time column (e.g. ns for EuRoC times in a TUM file)",
    )
    p.add_argument(
        "--dedupe",
        choices=("first", "last"),
        help="keep the first/last pose of repeated timestamps (default: refuse them)",
    )
    p.add_argument(
        "--max-diff",
        type=float,
        default=0.01,
        help="max time difference of a pair (s, default 0.01)",
    )
    p.add_argument(
        "--t-offset", type=float, default=0.0, help="seconds added to the estimate's times"
    )
    p.add_argument(
        "--interpolate",
        action="store_true",
        help="interpolate the reference at the estimate's times (linear + SLERP) instead of nearest",
    )
    p.add_argument(
        "--align-first",
        type=int,
        metavar="N",
        help="estimate the alignment on the first N pairs only",
    )
    p.add_argument(
        "--relation",
        choices=RELATIONS,
        default="trans",
        help="error of a pose: trans (m), angle_deg, angle_rad, rot (|R-I|), full (|E-I|)",
    )
    p.add_argument("--plot", metavar="FILE", help="save plots (PNG or PDF)")
    p.add_argument("--json", metavar="FILE", help="save the result as JSON (for `slam eval table`)")


def register(subparsers: Any) -> None:
    """Add `slam eval` with its subcommands."""
    fmt = argparse.RawDescriptionHelpFormatter
    parser = subparsers.add_parser(
        "eval",
        help="trajectory error against ground truth (APE, RPE, tables)",
        description=DESCRIPTION,
        formatter_class=fmt,
    )
    sub = parser.add_subparsers(dest="eval_command", metavar="{ape,rpe,table}")
    parser.set_defaults(func=lambda args: (parser.print_help(), 1)[1])

    ape = sub.add_parser(
        "ape",
        help="absolute pose error",
        description=APE_DESCRIPTION,
        epilog=APE_EPILOG,
        formatter_class=fmt,
    )
    _common(ape)
    ape.add_argument(
        "--align",
        choices=ALIGNMENTS,
        default="se3",
        help="alignment of the estimate (default se3; posyaw for VIO, sim3 for monocular)",
    )
    ape.set_defaults(func=run_ape)

    rpe = sub.add_parser(
        "rpe",
        help="relative pose error / drift",
        description=RPE_DESCRIPTION,
        epilog=RPE_EPILOG,
        formatter_class=fmt,
    )
    _common(rpe)
    rpe.add_argument(
        "--align",
        choices=ALIGNMENTS,
        default="none",
        help="alignment of the estimate (default none)",
    )
    rpe.add_argument(
        "--delta", type=float, nargs="+", default=[1.0], help="one or more deltas (default 1)"
    )
    rpe.add_argument(
        "--delta-unit",
        choices=("frames", "seconds", "metres"),
        default="frames",
        help="unit of --delta (metres: path length along the estimate, as evo)",
    )
    rpe.add_argument("--all-pairs", action="store_true", help="use all pairs, not consecutive ones")
    rpe.add_argument(
        "--rel-tol",
        type=float,
        default=0.1,
        help="relative tolerance of all-pairs deltas (default 0.1)",
    )
    rpe.add_argument(
        "--lengths",
        metavar="SPEC",
        help="drift over sub-trajectory lengths instead: kitti (100..800 m), rpg (10..50%% of the path) or 10,20,40",
    )
    rpe.set_defaults(func=run_rpe)

    table = sub.add_parser(
        "table",
        help="table of several results",
        description=TABLE_DESCRIPTION,
        epilog=TABLE_EPILOG,
        formatter_class=fmt,
    )
    table.add_argument("results", nargs="+", help="result files: our JSON or evo .zip")
    table.add_argument(
        "--format",
        choices=("markdown", "csv", "latex"),
        default="markdown",
        help="table format (default markdown)",
    )
    table.add_argument("--digits", type=int, default=4, help="decimals (default 4)")
    table.add_argument(
        "--out", metavar="FILE", help="write the table to FILE instead of printing it"
    )
    table.set_defaults(func=run_table)


def _options(args: argparse.Namespace) -> Any:
    from slam.evaluation.evaluate import EvalOptions

    return EvalOptions(
        ref_format=args.ref_format or args.format,
        est_format=args.est_format or args.format,
        ref_topic=args.ref_topic,
        est_topic=args.est_topic,
        ref_times=args.ref_times,
        est_times=args.est_times,
        dedupe=args.dedupe or "error",
        max_diff_s=args.max_diff,
        t_offset_s=args.t_offset,
        interpolate=args.interpolate,
        align=args.align,
        align_first=args.align_first,
        ref_time_unit=args.ref_time_unit,
        est_time_unit=args.est_time_unit,
    )


def _prepare(args: argparse.Namespace) -> Any:
    from slam.evaluation.evaluate import load_pair, prepare

    opts = _options(args)
    prepared = prepare(*load_pair(args.ref, args.est, opts), opts)
    for note in prepared.notes:
        print(note)
    return prepared


def _save(args: argparse.Namespace, results: list[Any], prepared: Any) -> None:
    if args.json:
        from slam.evaluation.results import write_json

        write_json(args.json, results)
        print(f"saved {args.json}")
    if args.plot:
        from slam.evaluation.plots import save_plots

        written = save_plots(args.plot, results, prepared)
        print("saved " + ", ".join(str(w) for w in written))


def run_ape(args: argparse.Namespace) -> int:
    """`slam eval ape`."""
    from slam.evaluation.evaluate import ape_of

    prepared = _prepare(args)
    result = ape_of(prepared, args.relation)
    print(result.summary())
    _save(args, [result], prepared)
    return 0


def run_rpe(args: argparse.Namespace) -> int:
    """`slam eval rpe`."""
    from slam.evaluation.evaluate import resolve_lengths, rpe_of, segments_of

    prepared = _prepare(args)
    if args.lengths:
        results = segments_of(prepared, resolve_lengths(args.lengths, prepared.ref_poses))
        for r in results:
            rot = r.extra["rot_deg_per_m"]
            print(
                f"{r.delta:8.1f} m: {len(r.errors):5d} segments, drift {r.stats['mean']:.4f} % "
                f"(median {r.stats['median']:.4f}), rotation {rot['mean']:.6f} deg/m"
            )
        n = sum(len(r.errors) for r in results)
        drift = sum(r.stats["mean"] * len(r.errors) for r in results) / n
        rot = sum(r.extra["rot_deg_per_m"]["mean"] * len(r.errors) for r in results) / n
        print(f"average over all {n} segments: drift {drift:.4f} %, rotation {rot:.6f} deg/m")
    else:
        results = [
            rpe_of(prepared, args.relation, d, args.delta_unit, args.all_pairs, args.rel_tol)
            for d in args.delta
        ]
        for r in results:
            print(r.summary())
    _save(args, results, prepared)
    return 0


def run_table(args: argparse.Namespace) -> int:
    """`slam eval table`."""
    from slam.evaluation.results import format_table, load_rows

    rows = [row for path in args.results for row in load_rows(path)]
    text = format_table(rows, args.format, args.digits)
    if args.out:
        from pathlib import Path

        Path(args.out).write_text(text)
        print(f"saved {args.out}")
    else:
        print(text, end="")
    return 0


def main(argv: list[str] | None = None) -> int:
    """Run `slam eval` alone (``python -m tools.cmd_eval ape REF EST``), without importing the
    other command modules; errors are handled as in ``tools.cli``."""
    import logging
    import sys

    from slam.core.errors import SlamError

    parser = argparse.ArgumentParser(prog="slam")
    sub = parser.add_subparsers(dest="command")
    register(sub)
    args = parser.parse_args(["eval", *(sys.argv[1:] if argv is None else argv)])
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    try:
        return int(args.func(args) or 0)
    except SlamError as exc:
        print(f"slam eval: error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    raise SystemExit(main())

"""`slam bench`: the benchmark suite, a markdown table and JSON per run."""

from __future__ import annotations

import argparse
from pathlib import Path

EPILOG = """\
examples:
  slam bench --out bench_out                      # the standard synthetic suite (cached)
  slam bench --out bench_out --quick 20           # every suite sequence cut to 20 s
  slam bench --out b2 --no-suite ~/data/V1_01_easy --config euroc-stereo-imu
  slam bench --out b3 --compare bench_out/results.json   # show the change since then
  slam bench --out b4 --repeats 3                 # medians over 3 runs of each
  slam bench --out b5 --only room-aggressive,hall # some of the suite
  slam bench --out clean --renders 3 --sequential   # 3 renders of each, deterministic runs
  slam bench --out real --renders 3 --sequential --camera realistic --compare clean/results.json
                                                  # realistic over clean: ATE ratios (x1.23)

The standard suite (generated once, cached in --cache-dir, deterministic):
  room-figure8 60 s, room-loop 80 s, room-aggressive 60 s (room-scale), hall 140 s (hall-scale),
  stereo 752x480 @ 20 Hz, IMU 200 Hz with EuRoC ADIS16448 noise.
Every run is `slam run SEQ --speed max` in its own process, without a viewer: a `slam batch`
(see its --help) over the suite, so a stopped benchmark resumes with the same --out, a failed
run is recorded and the others go on, and --repeats N gives medians (and the spread in
report.md, box plots in ate_boxplot.png).
Every suite sequence revisits earlier places: when loop closure is on, it is run a second time
with loop closure off (same configuration otherwise), for the columns "ATE loop off" and
"closed/off" (loop-closed ATE / ATE with loop closure off); --no-loop-baseline skips that.
--camera realistic renders the suite with `slam synth --camera realistic` (blur, auto-exposure,
vignetting, stereo gain, sensor noise, IMU vibration and scale errors), cached beside the clean
files. --renders K renders every suite sequence K times with seeds s, s+10, ... (the same
trajectory and scene; other noise and effects): one render is one draw, and a single SLAM run
amplifies small differences, so ratios are decided on medians over renders. --sequential runs
every frame through every stage in one thread: deterministic accuracy whatever the machine's
load, but its speed columns say nothing about real time.
"""


def register(subparsers: argparse._SubParsersAction) -> None:
    from datasets.synth.camera_model import CAMERA_BUNDLES

    p = subparsers.add_parser(
        "bench",
        help="run the benchmark suite and tabulate accuracy and speed",
        description="Run the pipeline over the standard synthetic suite (and any sequences "
        "given) and write results.md (a markdown table) and results.json.",
        epilog=EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("sequences", nargs="*", type=Path, help="extra sequences to run")
    p.add_argument("--out", type=Path, required=True, help="output folder")
    p.add_argument("--no-suite", action="store_true", help="skip the standard synthetic suite")
    p.add_argument(
        "--quick",
        type=float,
        default=None,
        metavar="S",
        help="cut every suite sequence to S seconds",
    )
    p.add_argument(
        "--cache-dir",
        type=Path,
        default=None,
        help="where suite sequences are cached (default ~/.cache/pyvislam/bench)",
    )
    p.add_argument("--config", default=None, help="preset or YAML passed to every slam run")
    p.add_argument(
        "--compare",
        type=Path,
        default=None,
        metavar="OLD.json",
        help="a previous results.json: show the change of every number",
    )
    p.add_argument(
        "--no-loop-baseline",
        action="store_true",
        help="do not re-run revisiting sequences with loop closure off (halves the time)",
    )
    p.add_argument(
        "--repeats",
        type=int,
        default=1,
        help="runs of every sequence (the table shows medians; report.md the spread)",
    )
    p.add_argument(
        "--only",
        default=None,
        metavar="NAMES",
        help="these suite sequences only, comma-separated (e.g. room-aggressive,hall)",
    )
    p.add_argument(
        "--renders",
        type=int,
        default=1,
        metavar="K",
        help="renders of every suite sequence (seeds s, s+10, ...); the table shows medians",
    )
    p.add_argument(
        "--camera",
        choices=CAMERA_BUNDLES,
        default="clean",
        help="suite rendered as slam synth --camera (default clean)",
    )
    p.add_argument(
        "--sequential",
        action="store_true",
        help="slam run --sequential: deterministic accuracy (speed columns meaningless)",
    )
    p.add_argument("--engine", choices=("local", "ray"), default="local", help="as slam batch")
    p.add_argument("--address", default="auto", help="--engine ray: as slam batch")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.add_argument(
        "--run-arg",
        action="append",
        default=[],
        metavar="ARG",
        help="extra argument for slam run (repeatable), e.g. --run-arg=--rerun=save:x.rrd",
    )
    p.set_defaults(func=handle)


def handle(args: argparse.Namespace) -> int:
    from slam.core.errors import InputError
    from tools.benchmark import (
        STANDARD_SUITE,
        SuiteEntry,
        default_cache_dir,
        run_benchmark,
        suite_variant,
    )

    if args.renders < 1 or args.repeats < 1:
        raise InputError("--renders and --repeats must be at least 1")
    suite = None
    if not args.no_suite:
        chosen: tuple[SuiteEntry, ...] = STANDARD_SUITE
        if args.only:
            names = [n.strip() for n in args.only.split(",") if n.strip()]
            unknown = sorted(set(names) - {e.name for e in STANDARD_SUITE})
            if unknown:
                known = ", ".join(e.name for e in STANDARD_SUITE)
                raise InputError(f"--only: no suite sequence {', '.join(unknown)} (known: {known})")
            chosen = tuple(e for e in STANDARD_SUITE if e.name in names)
        suite = suite_variant(chosen, args.quick, args.camera, args.renders)
    _, table, failed = run_benchmark(
        args.out,
        list(args.sequences),
        suite,
        args.cache_dir or default_cache_dir(),
        preset=args.config,
        extra_args=list(args.run_arg),
        compare=args.compare,
        loop_baseline=not args.no_loop_baseline,
        repeats=args.repeats,
        sequential=args.sequential,
        engine=args.engine,
        address=args.address,
        progress=not args.no_progress,
    )
    print()
    print(table)
    print(
        f"results in {args.out}/results.md and {args.out}/results.json; per run and with the "
        f"spread over repeats: {args.out}/report.md, runs.csv, ate_boxplot.png, trajectories.png"
    )
    return 1 if failed else 0

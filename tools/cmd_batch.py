"""`slam batch`: many runs (sequences x configurations x repeats), evaluated and tabulated."""

from __future__ import annotations

import argparse
from pathlib import Path

EPILOG = """\
examples:
  slam batch room.mcap hall.mcap --repeats 3 --out b1        # slam run's default config
  slam batch 'data/V1_0*' --config euroc-stereo-imu --config stereo-vo --out b2
  slam batch room.mcap --config euroc-stereo-imu --set loop_closure=false --out b3
  slam batch --spec batch.yaml --out b4                       # the same as a YAML file
  slam batch --spec batch.yaml --out b4                       # again: finished runs are kept
  slam batch --spec batch.yaml --engine ray --address auto --out b5   # on a Ray cluster

batch.yaml (every key but sequences optional):
  sequences: [room.mcap, "data/V1_0*", {path: hall.mcap, name: hall, configs: [vio]}]
  configs:
    - {name: vio, base: euroc-stereo-imu}
    - {name: no-loop, base: euroc-stereo-imu, set: {loop_closure: false}}
    - {name: fewer-features, set: {frontend.max_features: 120}}
  repeats: 3
  speed: max            # or sequential: true (deterministic, one thread per run)
  cpus_per_run: 2
  timeout_s: 1800       # a run still going after this is stopped and recorded as failed
  run_args: [--mesh]    # passed to every slam run
  path_map: {/home/me/data: /mnt/data}   # where Ray workers find the sequences

Every run is `slam run SEQ --speed S` (or --sequential) in its own process, declaring
--cpus-per-run CPUs: the local engine runs (cores // cpus-per-run) at once, Ray schedules
them on the cluster's nodes. Outputs in --out DIR, rewritten (atomically) as runs finish:
  runs/SEQ/CONFIG/repN/   slam run's outputs, slam_run.log, eval/ (APE JSON, aligned
                          trajectory), run.json (status, one-line error, numbers; written last)
  report.md, report.csv   per sequence x configuration: median (min-max) over the repeats of
                          ATE se3/posyaw, RPE, completion, real-time factor, latencies, memory
  runs.csv, runs.json     every run
  ate_boxplot.png         ATE per configuration per sequence, every repeat a dot
  trajectories.png        every run's trajectory over the ground truth (posyaw-aligned)
A batch that was stopped (Ctrl-C, SIGTERM, killed) is resumed by running it again with the
same --out: finished runs are skipped; failed runs are run again. A failed run (a missing
sequence, a crash, a timeout) is recorded with its error; the others go on.

Ray (pip install '.[ray]'): --address auto joins the cluster this machine is part of (started
with `ray start`), host:6379 or ray://host:10001 joins another; no cluster is started for you.
Every node needs pyvislam and the sequences at the same path (a shared folder) or --path-map.
"""


def register(subparsers: argparse._SubParsersAction) -> None:
    from tools.batch.engines import ENGINES

    p = subparsers.add_parser(
        "batch",
        help="many runs (sequences x configurations x repeats), evaluated and tabulated",
        description="Run `slam run` over sequences x configurations x repeats, locally or on a "
        "Ray cluster, evaluate every run against its ground truth (APE/RPE, se3 and posyaw) "
        "and gather everything into one folder with a report (markdown, CSV, box plots).",
        epilog=EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("sequences", nargs="*", metavar="SEQ", help="sequences or globs (quoted)")
    p.add_argument("--spec", type=Path, default=None, metavar="FILE.yaml", help="a batch spec")
    p.add_argument("--out", type=Path, required=True, help="output folder (reused to resume)")
    p.add_argument(
        "--config",
        action="append",
        default=None,
        metavar="PRESET|FILE",
        help="a configuration (repeatable; replaces the spec's); default: slam run's default",
    )
    p.add_argument(
        "--set",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="override a config key in every configuration (repeatable), e.g. "
        "--set loop_closure=false --set frontend.max_features=120",
    )
    p.add_argument("--repeats", type=int, default=None, help="runs of each pair (default 1)")
    play = p.add_mutually_exclusive_group()
    play.add_argument("--speed", default=None, help="slam run --speed: 1, 4, ..., max (default)")
    play.add_argument(
        "--sequential",
        action="store_true",
        default=None,
        help="every run single-threaded in time order, as fast as it goes (deterministic)",
    )
    p.add_argument("--engine", choices=ENGINES, default="local", help="where runs execute")
    p.add_argument(
        "--address",
        default="auto",
        help="--engine ray: auto (this machine's cluster), HOST:PORT or ray://HOST:10001",
    )
    p.add_argument(
        "--cpus-per-run",
        type=float,
        default=None,
        help="CPUs each run declares (default 2: the front end and the worker processes)",
    )
    p.add_argument(
        "--jobs",
        type=int,
        default=None,
        help="--engine local: runs at once (default: cores // cpus-per-run, at least 1)",
    )
    p.add_argument("--timeout", type=float, default=None, metavar="S", help="per-run limit")
    p.add_argument(
        "--run-arg",
        action="append",
        default=None,
        metavar="ARG",
        help="extra argument for every slam run (repeatable), e.g. --run-arg=--mesh",
    )
    p.add_argument(
        "--path-map",
        action="append",
        default=[],
        metavar="HERE=THERE",
        help="Ray workers read sequences under HERE at THERE (repeatable)",
    )
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.set_defaults(func=handle)


def spec_from_args(args: argparse.Namespace):  # -> BatchSpec
    """The spec file's (if any), with the command line's sequences added and options applied."""
    import yaml

    from slam.core.errors import InputError
    from tools.batch.spec import (
        DEFAULT_CONFIG,
        BatchSpec,
        ConfigChoice,
        apply_options,
        expand_sequences,
        load_spec,
        parse_configs,
    )

    spec = load_spec(args.spec) if args.spec else BatchSpec([], [])
    if args.sequences:
        spec.sequences += expand_sequences(list(args.sequences), Path.cwd())
    if args.config:
        spec.configs = parse_configs(list(args.config), Path.cwd())
    if not spec.configs:
        spec.configs = [ConfigChoice(DEFAULT_CONFIG)]
    if not spec.sequences:
        raise InputError("no sequences: give SEQ... or --spec FILE.yaml")
    sets = {}
    for item in args.set:
        key, eq, value = item.partition("=")
        if not eq or not key:
            raise InputError(f"--set {item!r}: expected KEY=VALUE, e.g. loop_closure=false")
        sets[key.strip()] = yaml.safe_load(value)
    if sets:
        spec.configs = [ConfigChoice(c.name, c.base, {**c.overrides, **sets}) for c in spec.configs]
    path_map = {}
    for item in args.path_map:
        here, eq, there = item.partition("=")
        if not eq or not here or not there:
            raise InputError(f"--path-map {item!r}: expected HERE=THERE")
        path_map[here] = there
    return apply_options(
        spec,
        {
            "repeats": args.repeats,
            "speed": args.speed,
            "sequential": args.sequential,
            "cpus_per_run": args.cpus_per_run,
            "timeout_s": args.timeout,
            "run_args": args.run_arg,
            "path_map": path_map or None,
        },
    )


def handle(args: argparse.Namespace) -> int:
    from tools.batch.runner import run_batch

    spec = spec_from_args(args)
    result = run_batch(
        spec,
        args.out,
        engine=args.engine,
        address=args.address,
        jobs=args.jobs,
        progress=not args.no_progress,
    )
    print((args.out / "report.md").read_text())
    print(
        f"{len(result.tasks)} runs: {result.skipped} finished before, {result.ran} run now "
        f"({result.failed} failed) in {result.wall_s:.0f} s; report in {args.out}/report.md, "
        f"report.csv, ate_boxplot.png, trajectories.png"
    )
    return 1 if result.failed else 0

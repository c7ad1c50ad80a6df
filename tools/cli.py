"""The `slam` command: one entry point, one module per subcommand.

Each ``tools/cmd_*.py`` module exposes ``register(subparsers)`` which adds its parser and sets
``func`` to a handler ``(args) -> int``. Only the module of the command being run is imported
(start-up time matters: `slam eval` must beat evo_ape, and some commands import scipy, GTSAM
or OpenCV); the others appear in `slam --help` through their one-line summary below.
Known user errors (``SlamError``) end in one line on stderr and exit status 2; nothing else is
caught, so real bugs keep their traceback.
"""

from __future__ import annotations

import argparse
import importlib
import logging
import os
import sys

from slam.core.errors import SlamError

COMMANDS: dict[str, tuple[str, str]] = {
    "synth": ("tools.cmd_synth", "generate a synthetic stereo+IMU sequence with ground truth"),
    "info": ("tools.cmd_info", "summarise a sequence: topics, rates, gaps, calibration"),
    "convert": ("tools.cmd_convert", "write any sequence source as our MCAP"),
    "run": ("tools.cmd_run", "track a sequence; trajectory, keyframes, stats, live rerun view"),
    "config": ("tools.cmd_config", "every configuration key with its default, unit and doc"),
    "eval": ("tools.cmd_eval", "trajectory error (APE, RPE, drift) against ground truth"),
    "batch": ("tools.cmd_batch", "many runs (sequences x configs x repeats), locally or on Ray"),
    "bench": ("tools.cmd_bench", "run the benchmark suite and tabulate accuracy and speed"),
    "fuse": ("tools.cmd_fuse", "dense mesh by TSDF fusion (RGB-D folder, or sequence + poses)"),
    "vocab": ("tools.cmd_vocab", "train or inspect a bag-of-words vocabulary"),
    "pgo": ("tools.cmd_pgo", "optimise a g2o 3-D pose graph"),
    "calib": ("tools.cmd_calib", "check a recording's camera-IMU time offset and rotation"),
}

DESCRIPTION = """\
Stereo-inertial SLAM: turn a recorded camera+IMU sequence into a trajectory, a loop-closed map
and a dense mesh; watch it live in rerun; score it against ground truth.

Typical session:
  slam synth room.mcap --profile figure8 --duration 30   # make a sequence with ground truth
  slam info room.mcap                                    # what is in it
  slam run room.mcap --out run1 --rerun save:run1.rrd    # track it
  slam eval ape room.mcap run1 --align se3 --plot ape.png

Sequences: our MCAP files, ROS 2 bags recorded as MCAP (+ Kalibr calibration), EuRoC and TUM-VI
folders. Run `slam CMD --help` for the details of each command.
"""


def _requested_command(argv: list[str]) -> str | None:
    for token in argv:
        if not token.startswith("-"):
            return token
    return None


def build_parser(argv: list[str] | None = None) -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="slam",
        description=DESCRIPTION,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("-v", "--verbose", action="store_true", help="debug logging")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    wanted = _requested_command(sys.argv[1:] if argv is None else argv)
    for name, (module_name, summary) in COMMANDS.items():
        if name == wanted:
            importlib.import_module(module_name).register(sub)
        else:
            sub.add_parser(name, help=summary, description=summary)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser(argv)
    args = parser.parse_args(argv)
    logging.basicConfig(
        level=logging.DEBUG if args.verbose else logging.INFO,
        format="%(levelname)s %(name)s: %(message)s",
    )
    if not getattr(args, "func", None):
        parser.print_help()
        return 1
    try:
        return int(args.func(args) or 0)
    except SlamError as exc:
        print(f"slam {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"slam {args.command}: interrupted", file=sys.stderr)
        return 130
    except BrokenPipeError:  # `slam config show | head`: the reader went away; not an error
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())  # no flush error at exit
        return 141


if __name__ == "__main__":
    sys.exit(main())

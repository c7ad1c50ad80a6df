"""The `slam` command: one entry point, one module per subcommand.

Each ``tools/cmd_*.py`` module exposes ``register(subparsers)`` which adds its parser and sets
``func`` to a handler ``(args) -> int``. Known user errors (``SlamError``) end in one line on
stderr and exit status 2; nothing else is caught, so real bugs keep their traceback.
"""

from __future__ import annotations

import argparse
import importlib
import logging
import sys

from slam.errors import SlamError

COMMAND_MODULES = (
    "tools.cmd_synth",
    "tools.cmd_info",
    "tools.cmd_convert",
    "tools.cmd_run",
    "tools.cmd_eval",
    "tools.cmd_bench",
    "tools.cmd_fuse",
    "tools.cmd_vocab",
    "tools.cmd_pgo",
)

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


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="slam",
        description=DESCRIPTION,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("-v", "--verbose", action="store_true", help="debug logging")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name in COMMAND_MODULES:
        try:
            module = importlib.import_module(name)
        except ModuleNotFoundError as exc:  # a command not built yet in this checkout
            if exc.name == name:
                continue
            raise
        module.register(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
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


if __name__ == "__main__":
    sys.exit(main())

"""`slam info SEQ`: what is in a sequence (topics, rates, gaps, calibration, ground truth)."""

from __future__ import annotations

import argparse

from datasets.info import describe
from tools.seq_args import SEQUENCE_HELP, add_sequence_args, source_options

DESCRIPTION = (
    """\
Summarise a sequence: topics with types, counts and rates (MCAP), frame and IMU counts, rates,
spans and gaps, the span where frames and IMU overlap (what a run uses), the calibration
(intrinsics, distortion, extrinsics, IMU noise, time offset), the ground truth (or, when the
sequence has none, the trajectory files in its folder to pass with --gt), and every data-quality
warning found while reading. Counts are what a run will get: frames in corrupt chunks or with a
missing image file are left out (and named in a warning); a truncated file's warning counts the
frames and seconds it lost.

An MCAP file that is not a usable sequence (e.g. odometry topics only, or no calibration) still
gets its topic list, then the reason it cannot be used (exit status 2).

"""
    + SEQUENCE_HELP
    + """
examples:
  slam info room.mcap
  slam info ../shared/data/euroc_v101_micro
  slam info bag.mcap --left-topic /camera/left/image_raw --right-topic /camera/right/image_raw \\
      --imu-topic /imu/data --camchain camchain.yaml --imu-yaml imu.yaml
"""
)


def run(args: argparse.Namespace) -> int:
    lines, usable = describe(args.seq, **source_options(args))
    print("\n".join(lines))
    return 0 if usable else 2


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "info",
        help="summarise a sequence (topics, rates, spans, gaps, calibration, ground truth)",
        description=DESCRIPTION,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    add_sequence_args(p)
    p.set_defaults(func=run)

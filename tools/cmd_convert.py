"""`slam convert SRC OUT.mcap`: write any sequence as our self-contained ROS 2 MCAP."""

from __future__ import annotations

import argparse
import logging

from datasets.mcap_io import write_sequence_mcap
from slam.core.errors import InputError
from tools.seq_args import SEQUENCE_HELP, add_sequence_args, open_from_args

log = logging.getLogger(__name__)

DESCRIPTION = (
    """\
Convert a sequence to our MCAP file: ROS 2 profile, cdr messages, ros2msg schemas, zstd chunks,
topics /cam0/image_raw, /cam1/image_raw (mono8), /cam0/camera_info, /cam1/camera_info, /imu0,
/groundtruth/pose, and the full calibration as a metadata record, so the one file is
self-contained (`ros2 bag info`, rosbags, Foxglove and rerun open it too). Colour and compressed
images become 8-bit grey. The output is written atomically (no partial file on failure).

"""
    + SEQUENCE_HELP
    + """
examples:
  slam convert ../shared/data/euroc_v101_micro v101_micro.mcap
  slam convert recorded_bag/ out.mcap --left-topic /left/image_raw/compressed \\
      --right-topic /right/image_raw/compressed --imu-topic /imu --camchain camchain.yaml \\
      --imu-yaml imu.yaml
"""
)


def run(args: argparse.Namespace) -> int:
    if not str(args.out).endswith(".mcap"):
        raise InputError(f"output {args.out} should end in .mcap")
    seq = open_from_args(args, positional="src")
    write_sequence_mcap(seq, args.out, progress=not args.quiet, compression=args.compression)
    print(
        f"wrote {args.out}: {seq.num_frames} frames, {seq.num_imu} IMU samples, "
        f"{len(seq.ground_truth) if seq.ground_truth is not None else 0} ground-truth poses"
        + (f", {len(seq.warnings)} warning(s) while reading" if seq.warnings else "")
    )
    return 0


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "convert",
        help="write any sequence (EuRoC/TUM-VI folder, ROS 2 bag) as our MCAP",
        description=DESCRIPTION,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    add_sequence_args(p, positional="src")
    p.add_argument("out", metavar="OUT.mcap", help="output file")
    p.add_argument(
        "--compression",
        choices=("zstd", "lz4", "none"),
        default="zstd",
        help="chunk compression: zstd (default, smallest file), lz4 (faster to read), none",
    )
    p.add_argument("-q", "--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=run)

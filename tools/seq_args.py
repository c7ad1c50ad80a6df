"""Command-line options for choosing and opening a sequence, shared by every command that reads
one (``slam info``, ``slam convert``, ``slam run``, ``slam eval``)."""

from __future__ import annotations

import argparse
from typing import Any

from datasets.open import open_sequence
from datasets.sequence import Sequence

SEQUENCE_HELP = """\
SEQ can be:
  our MCAP file            (written by `slam synth` / `slam convert`; self-contained)
  a ROS 2 bag as MCAP      (a .mcap file or a rosbag2 folder holding one; pick topics with
                            --left-topic/--right-topic/--imu-topic/--gt-topic, calibration with
                            --camchain camchain.yaml --imu-yaml imu.yaml from Kalibr)
  an EuRoC / TUM-VI folder (the ASL layout: mav0/cam0/data.csv, sensor.yaml files)
"""


def add_sequence_args(parser: argparse.ArgumentParser, *, positional: str = "seq") -> None:
    """Add SEQ and the source options (topics, Kalibr calibration, ground-truth override)."""
    parser.add_argument(
        positional, metavar="SEQ", help="sequence to read (see the description above)"
    )
    g = parser.add_argument_group("sequence source options")
    g.add_argument("--left-topic", help="left/only camera topic (default /cam0/image_raw)")
    g.add_argument("--right-topic", help="right camera topic (default /cam1/image_raw if present)")
    g.add_argument("--imu-topic", help="IMU topic (default /imu0 if present)")
    g.add_argument("--gt-topic", help="ground-truth pose topic (default /groundtruth/pose)")
    g.add_argument("--camchain", metavar="YAML", help="Kalibr camchain.yaml (cameras, T_cam_imu)")
    g.add_argument("--imu-yaml", metavar="YAML", help="Kalibr imu.yaml (IMU noise model)")
    g.add_argument(
        "--gt", metavar="FILE", help="ground truth file (EuRoC csv or TUM txt) to use instead"
    )


def source_options(args: argparse.Namespace) -> dict[str, Any]:
    """The :func:`add_sequence_args` options as keyword arguments of ``open_sequence``."""
    return {
        "left_topic": args.left_topic,
        "right_topic": args.right_topic,
        "imu_topic": args.imu_topic,
        "gt_topic": args.gt_topic,
        "camchain": args.camchain,
        "imu_yaml": args.imu_yaml,
        "gt_path": args.gt,
    }


def open_from_args(args: argparse.Namespace, *, positional: str = "seq") -> Sequence:
    """Open the sequence described by :func:`add_sequence_args` options."""
    return open_sequence(getattr(args, positional), **source_options(args))

"""Open any supported sequence by path: our MCAP, a ROS 2 MCAP bag, or an EuRoC/TUM-VI folder."""

from __future__ import annotations

import os
from pathlib import Path

from datasets.euroc import EurocSequence, find_mav0
from datasets.kalibr import load_kalibr
from datasets.mcap_io import McapSequence
from datasets.mcap_scan import MAGIC
from datasets.ros2bag import (
    DEFAULT_GT_TOPIC,
    DEFAULT_IMU_TOPIC,
    DEFAULT_LEFT_TOPIC,
    DEFAULT_RIGHT_TOPIC,
    Ros2McapSequence,
    TopicSelection,
)
from datasets.sequence import Sequence
from slam.core.errors import InputError

SUPPORTED = (
    "an MCAP file (ours, or a ROS 2 bag recorded as MCAP), a ROS 2 bag folder holding one "
    ".mcap file, or an EuRoC/TUM-VI folder (mav0/cam0/data.csv)"
)


def find_mcap(path: str | os.PathLike[str]) -> Path | None:
    """The MCAP file of ``path``: itself, or the single .mcap inside a rosbag2 folder."""
    p = Path(path)
    if p.is_file():
        with open(p, "rb") as fh:
            return p if fh.read(8) == MAGIC else None
    if p.is_dir():
        found = sorted(p.glob("*.mcap"))
        if len(found) == 1:
            return found[0]
        if len(found) > 1:
            raise InputError(
                f"{p} holds {len(found)} .mcap files (split bag); pass one file: "
                + ", ".join(f.name for f in found[:5])
            )
    return None


def open_sequence(
    path: str | os.PathLike[str],
    *,
    left_topic: str | None = None,
    right_topic: str | None = None,
    imu_topic: str | None = None,
    gt_topic: str | None = None,
    camchain: str | os.PathLike[str] | None = None,
    imu_yaml: str | os.PathLike[str] | None = None,
    gt_path: str | os.PathLike[str] | None = None,
    strict: bool = False,
) -> Sequence:
    """Open ``path`` as a :class:`Sequence`, choosing the reader from what is there.

    MCAP: topics default to ours (``/cam0/image_raw``, ``/cam1/image_raw``, ``/imu0``,
    ``/groundtruth/pose``), or to the ``rostopic`` entries of the Kalibr files when given; a
    topic named explicitly must exist. Calibration: the Kalibr files when given, else the
    file's embedded record. ``gt_path``: a ground-truth file (EuRoC csv or TUM text) that
    replaces the one found in the source. ``strict``: refuse input that would lose frames (a
    listed image file missing, a truncated file, a corrupt chunk) instead of skipping them
    with a warning.
    """
    p = Path(path)
    if not p.exists():
        raise InputError(f"{p}: no such file or folder")
    if p.is_file() and p.stat().st_size == 0:
        raise InputError(f"{p} is empty (0 bytes); expected {SUPPORTED}")
    if find_mav0(p) is not None:
        if any(x is not None for x in (left_topic, right_topic, imu_topic, gt_topic)):
            raise InputError(f"{p} is an EuRoC/TUM-VI folder: topic options do not apply to it")
        return EurocSequence(p, gt_path=gt_path, strict=strict)
    mcap = find_mcap(p)
    if mcap is None:
        if p.suffix == ".db3" or (p.is_dir() and any(p.glob("*.db3"))):
            raise InputError(
                f"{p} is a ROS 2 bag in SQLite format; convert it to MCAP first "
                "(`rosbags-convert --src BAG --dst OUT --dst-storage mcap`, or record with "
                "`ros2 bag record --storage mcap`)"
            )
        if p.suffix == ".bag":
            raise InputError(
                f"{p} is a ROS 1 bag; convert it to a ROS 2 MCAP bag first "
                "(`rosbags-convert --src FILE.bag --dst OUT --dst-storage mcap`)"
            )
        raise InputError(f"{p}: not a sequence I can read; expected {SUPPORTED}")

    calibration = None
    kalibr_topics: tuple[str | None, ...] = ()
    kalibr_imu_topic = None
    if camchain is not None:
        kal = load_kalibr(camchain, imu_yaml)
        calibration = kal.calibration
        kalibr_topics, kalibr_imu_topic = kal.camera_topics, kal.imu_topic
    elif imu_yaml is not None:
        raise InputError("--imu-yaml needs --camchain too (the camera calibration)")

    def pick(explicit: str | None, from_kalibr: str | None, default: str) -> str:
        return explicit or from_kalibr or default

    required = tuple(
        role
        for role, given in (("right", right_topic), ("imu", imu_topic), ("gt", gt_topic))
        if given is not None
    )
    topics = TopicSelection(
        left=pick(left_topic, kalibr_topics[0] if kalibr_topics else None, DEFAULT_LEFT_TOPIC),
        right=pick(
            right_topic, kalibr_topics[1] if len(kalibr_topics) > 1 else None, DEFAULT_RIGHT_TOPIC
        ),
        imu=pick(imu_topic, kalibr_imu_topic, DEFAULT_IMU_TOPIC),
        gt=pick(gt_topic, None, DEFAULT_GT_TOPIC),
    )
    seq: Ros2McapSequence
    if calibration is None and not required and left_topic is None:
        seq = McapSequence(mcap, topics=topics, strict=strict)
    else:
        seq = Ros2McapSequence(
            mcap, topics=topics, calibration=calibration, required=required, strict=strict
        )
    if gt_path is not None:
        from datasets.euroc import read_trajectory_file

        seq.ground_truth = read_trajectory_file(gt_path)
    return seq

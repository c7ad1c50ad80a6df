"""`slam calib check SEQ`: the camera-IMU time offset and rotation from the data, against the
calibration the sequence came with."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from tools.seq_args import SEQUENCE_HELP, add_sequence_args, open_from_args

DESCRIPTION = """\
Check a recording's camera-IMU calibration against its own data.

  check   estimate the camera-IMU time offset and the camera-IMU rotation from cam0's images
          and the gyro, compare them with the calibration, and say what to do

Run `slam calib check --help` for the method and examples.
"""

CHECK_DESCRIPTION = (
    """\
Estimate, from the recording alone, the camera-IMU time offset and the rotation between camera
and IMU, and compare them with the calibration the sequence came with.

How: cam0's rotation between consecutive frames (KLT tracks, essential matrix or homography
with RANSAC), against the gyro integrated over the same interval shifted by a trial offset.
The offset is where the two rotation rates correlate best (1 ms grid, parabola through the
peak), refined on the whole rotation vectors; the rotation is the least-squares (SVD) rotation
between the gyro's and the camera's rotation vectors (hand-eye). Spreads are bootstrapped over
frame pairs. The offset is reported on top of the one the calibration already applies, in
Kalibr's convention (an image stamped t shows the scene at IMU time t + offset). Where the
recording gives each image's exposure (our MCAP's /cam0/exposure), an image is taken at the
middle of it, as `slam run` does, so the offset is what is left beyond the exposure.

Needs rotation: 20 s or more of the rig turned back and forth about at least two axes (0.5-2
rad/s), sharp textured images. A still recording, rotation about one axis only, or an offset
beyond --max-offset each get a one-line answer (exit 2), never a number.
Exit status: 0 the calibration agrees, 1 it is wrong (flagged lines say how), 2 no answer.
Cost: ~30-60 ms per frame (2 cores).

"""
    + SEQUENCE_HELP
    + """
examples:
  slam calib check rig.mcap
  slam calib check late.mcap --max-offset 200 --json check.json
  slam calib check ../shared/data/euroc_v101_micro      # almost still: says so
  slam synth late.mcap --profile aggressive --duration 20 --time-offset 15 \\
      --calib-rotation-error 0,2,0 && slam calib check late.mcap
"""
)


def run_check(args: argparse.Namespace) -> int:
    from tqdm import tqdm

    from slam.calib.check import check_calibration
    from slam.core.atomic import write_atomic
    from slam.core.errors import InputError

    if not 1.0 <= args.max_offset <= 1000.0:
        raise InputError(f"--max-offset must be within [1, 1000] ms, got {args.max_offset}")
    if args.duration is not None and args.duration <= 0:
        raise InputError(f"--duration must be positive, got {args.duration}")
    seq = open_from_args(args)
    imu = seq.imu()
    times = seq.frame_times_ns()
    if len(times) == 0:
        raise InputError(f"{args.seq}: no camera frames")
    t_start = int(times[0]) + int(args.start * 1e9)
    t_stop = None if args.duration is None else t_start + int(args.duration * 1e9)
    count = int(((times >= t_start) & (times <= (t_stop or times[-1]))).sum())

    def frames():  # type: ignore[no-untyped-def]
        bar = tqdm(total=count, desc="calib check", unit="frame", disable=args.quiet)
        for frame in seq.iter_frames():
            if frame.t_ns < t_start:
                continue
            if t_stop is not None and frame.t_ns > t_stop:
                break
            bar.update(1)
            yield frame.mid_exposure_ns, frame.left  # the time the image shows
        bar.close()

    result = check_calibration(
        frames(), imu.t_ns, imu.gyro_rad_s, seq.calibration, round(args.max_offset * 1e6)
    )
    print("\n".join(result.report()))
    if args.json is not None:
        write_atomic(Path(args.json), json.dumps(result.to_dict(), indent=2).encode())
    return 0 if result.ok else 1


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "calib",
        help="check a recording's camera-IMU time offset and rotation",
        description=DESCRIPTION,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    sub = p.add_subparsers(dest="calib_command", metavar="ACTION", required=True)
    c = sub.add_parser(
        "check",
        help="time offset and camera-IMU rotation from the data, against the calibration",
        description=CHECK_DESCRIPTION,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    add_sequence_args(c)
    c.add_argument(
        "--max-offset", type=float, default=100.0, metavar="MS", help="search +-MS (default 100)"
    )
    c.add_argument("--start", type=float, default=0.0, metavar="S", help="skip the first S s")
    c.add_argument("--duration", type=float, metavar="S", help="use S seconds (default: all)")
    c.add_argument("--json", type=Path, metavar="F", help="also write the numbers as JSON")
    c.add_argument("-q", "--quiet", action="store_true", help="no progress bar")
    c.set_defaults(func=run_check)

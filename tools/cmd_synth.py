"""`slam synth OUT.mcap`: render a synthetic stereo-inertial sequence with exact ground truth."""

from __future__ import annotations

import argparse
from pathlib import Path

from datasets.synth.trajectories import PROFILES
from slam.core.errors import InputError

DESCRIPTION = """\
Render a synthetic stereo-inertial sequence with exact ground truth and write it as our MCAP
file (ROS 2 profile: /cam0/image_raw, /cam1/image_raw, /imu0, /groundtruth/pose, calibration).

The world is a textured room (8 x 6 x 3 m; the `hall` profile uses a 30 x 10 x 3 m hall) with a
few boxes for parallax, every face covered with crops of real photographs. Cameras: stereo
752x480 at 20 Hz with EuRoC's intrinsics, radtan distortion and camera-IMU extrinsics (0.11 m
baseline). IMU: 200 Hz from the trajectory's analytic derivatives, plus white noise and bias
random walk with EuRoC's ADIS16448 figures (--no-imu-noise for exact readings). The body is
still for the first 2 s (static IMU initialisation works), unless --moving-start.

profiles (default duration):
  figure8     slow figure-8 in the room, <= 0.8 m/s (40 s)
  loop        an ellipse looking outwards; revisits its start pose at t = 78 s (80 s)
  aggressive  fast figure-8 with shakes: <= 2.5 m/s, 4 m/s^2, 3 rad/s (30 s)
  hall        11 x 3 m ellipse in the hall, ~117 m of path (140 s)
  --from-trajectory FILE  any TUM or EuRoC ground-truth trajectory (cubic splines), in a room
                          fitted around it; --imu-csv adds its real EuRoC IMU stream instead
                          of the simulated one

Deterministic: the same options and --seed give bit-identical files. --seed drives the noise;
the scene (textures, boxes) is fixed by --scene-seed.

examples:
  slam synth room.mcap                                    # figure8, 40 s
  slam synth loop.mcap --profile loop --seed 3
  slam synth fast.mcap --profile aggressive --duration 20 --no-imu-noise
  slam synth biased.mcap --gyro-bias 0.002,-0.001,0.003 --accel-bias 0.05,0.02,-0.04
  slam synth lost.mcap --blackout 10:2                    # frames black from 10 s to 12 s
  slam synth dense.mcap --duration 10 --depth-dir dense_depth --mesh scene.ply
  slam synth v101.mcap --from-trajectory mav0/state_groundtruth_estimate0/data.csv \\
      --imu-csv mav0/imu0/data.csv
"""


def parse_blackout(text: str | None) -> tuple[float, float] | None:
    """``START:DUR`` in seconds -> (start_s, duration_s)."""
    if text is None:
        return None
    try:
        start, dur = (float(v) for v in text.split(":"))
    except ValueError as exc:
        raise InputError(
            f"--blackout expects START:DUR in seconds (e.g. 10:2), got {text!r}"
        ) from exc
    if start < 0 or dur <= 0:
        raise InputError(f"--blackout needs START >= 0 and DUR > 0, got {text!r}")
    return start, dur


def parse_vector3(text: str | None, option: str) -> tuple[float, float, float] | None:
    """``X,Y,Z`` -> a 3-tuple of floats."""
    if text is None:
        return None
    try:
        x, y, z = (float(v) for v in text.split(","))
    except ValueError as exc:
        raise InputError(
            f"{option} expects three comma-separated numbers X,Y,Z, got {text!r}"
        ) from exc
    return x, y, z


def run(args: argparse.Namespace) -> int:
    from datasets.synth.export import run_synth

    result = run_synth(
        args.out,
        profile=args.profile,
        duration_s=args.duration,
        seed=args.seed,
        scene_seed=args.scene_seed,
        trajectory_file=args.from_trajectory,
        imu_csv=args.imu_csv,
        imu_noise=not args.no_imu_noise,
        blackout=parse_blackout(args.blackout),
        moving_start=args.moving_start,
        aliasing=args.aliasing,
        pixel_noise_std=args.pixel_noise,
        gyro_bias0_rad_s=parse_vector3(args.gyro_bias, "--gyro-bias"),
        accel_bias0_m_s2=parse_vector3(args.accel_bias, "--accel-bias"),
        depth_dir=args.depth_dir,
        mesh_path=args.mesh,
        progress=not args.quiet,
    )
    print(
        f"wrote {result.mcap_path}: {result.num_frames} stereo frames, {result.num_imu} IMU "
        f"samples, {result.duration_s:.1f} s, path {result.path_length_m:.1f} m"
    )
    if result.depth_images:
        print(f"wrote {result.depth_images} depth images (uint16 mm) to {args.depth_dir}")
    if result.mesh_path is not None:
        print(f"wrote scene mesh {result.mesh_path}")
    return 0


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "synth",
        help="render a synthetic stereo+IMU sequence with exact ground truth",
        description=DESCRIPTION,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("out", metavar="OUT.mcap", type=Path, help="output MCAP file")
    p.add_argument("--profile", default="figure8", choices=PROFILES, help="motion profile")
    p.add_argument("--duration", type=float, metavar="S", help="seconds (default: per profile)")
    p.add_argument("--seed", type=int, default=0, help="noise seed (IMU and pixel noise)")
    p.add_argument("--scene-seed", type=int, default=0, help="textures and boxes of the scene")
    p.add_argument(
        "--from-trajectory", metavar="FILE", help="TUM or EuRoC ground-truth file to follow"
    )
    p.add_argument("--imu-csv", metavar="FILE", help="real EuRoC imu0/data.csv to use instead")
    p.add_argument("--no-imu-noise", action="store_true", help="exact IMU (no noise, no bias)")
    p.add_argument("--gyro-bias", metavar="X,Y,Z", help="initial gyro bias, rad/s (default 0)")
    p.add_argument("--accel-bias", metavar="X,Y,Z", help="initial accel bias, m/s^2 (default 0)")
    p.add_argument("--blackout", metavar="START:DUR", help="black frames in [START, START+DUR) s")
    p.add_argument("--moving-start", action="store_true", help="start in motion (no still 2 s)")
    p.add_argument(
        "--aliasing", action="store_true", help="identical boxes and long walls (loop-closure trap)"
    )
    p.add_argument("--pixel-noise", type=float, default=0.0, metavar="SIGMA", help="grey levels")
    p.add_argument(
        "--depth-dir",
        metavar="DIR",
        type=Path,
        help="also write cam0 depth PNGs (uint16 mm; named by time in ns, zero-padded to 19 "
        "digits as EuRoC's images, so they sort) and depth.json",
    )
    p.add_argument("--mesh", metavar="FILE.ply", type=Path, help="also write the scene mesh")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress bars")
    p.set_defaults(func=run)

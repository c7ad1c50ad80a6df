"""`slam synth OUT.mcap`: render a synthetic stereo-inertial sequence with exact ground truth."""

from __future__ import annotations

import argparse
import dataclasses
from pathlib import Path
from typing import TYPE_CHECKING

from datasets.synth.trajectories import PROFILES
from slam.core.errors import InputError

if TYPE_CHECKING:
    from datasets.synth.camera_model import CameraEffects
    from datasets.synth.imu_sim import ImuEffects

DESCRIPTION = """\
Render a synthetic stereo-inertial sequence with exact ground truth and write it as our MCAP
file (ROS 2 profile: /cam0/image_raw, /cam1/image_raw, /imu0, /groundtruth/pose, calibration).
Ground truth is at 200 Hz and, when images have an exposure (blur), also at each image's
mid-exposure time, so evo's and `slam eval`'s nearest-pose association is exact.

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
                          of the simulated one. The images follow FILE, the IMU the real
                          motion: FILE's orientation must be accurate (EuRoC's own V1_01
                          ground truth is not; OpenVINS's recomputed V1_01_easy.txt is). The
                          gyro is checked against FILE's rotation (a warning above 0.8 deg
                          per 5 s; see BENCHMARKS.md), the accelerometer's scale against its
                          positions (reported). --imu-csv-on-trajectory makes the IMU from
                          FILE instead, keeping the real one's bias drift and noise: the real
                          V1_01 IMU and its ground truth disagree by ~1 % in scale and by
                          errors a slow bias does not describe (BENCHMARKS.md, v101imu18)

A real camera and a real rig (off by default; --camera realistic switches on a bundle, and
each option below overrides its part):
  --camera realistic   auto-exposure (0.2-10 ms, 3 dB gain steps) over a scene whose
                       illumination drifts x0.3-x3.3 (24 s period), motion blur over each
                       exposure, 30 % corner vignetting (cos^4), right camera 3 % brighter,
                       read noise 1.2 grey levels + shot noise (40 e-/grey level); IMU:
                       0.8 m/s^2 and 0.02 rad/s RMS propeller vibration near 73 Hz, 0.3 %
                       scale errors, 1 mrad axis misalignment. No time offset, no rolling shutter.
  --exposure MS        fixed exposure: motion blur over [stamp - MS, stamp] (sub-frames
                       rendered at most 1.5 px of image motion apart, up to 24)
  --auto-exposure      exposure and gain follow the illumination (--illumination A: its
                       log amplitude, 1.2 = x0.3..x3.3); each gain step brightens or darkens
                       one frame abruptly by the step
  --vignetting F       corners darkened by F (0.3 = to 70 %), cos^4 of the field angle
  --stereo-gain R      right camera's gain over the left's (1.03 = 3 % brighter)
  --read-noise SIGMA, --shot-noise GL   sensor noise: sigma^2 = (SIGMA G)^2 + GL G signal
  --line-delay US      rolling shutter: each row ends its exposure US microseconds after
                       the one above (the middle row at the stamp)
  --time-offset MS     an image stamped t shows the scene at IMU time t + MS (the file's
                       calibration still says 0: what `slam calib check` should find)
  --calib-rotation-error X,Y,Z   the file's camera-IMU rotation is off by this rotation
                       vector (degrees); the images use the true one
  --imu-vibration ACC,GYRO,HZ    vibration RMS (m/s^2, rad/s) near HZ (1.5 Hz wander)
  --imu-scale-error F, --imu-misalignment MRAD   per-axis scale (std, fraction) and
                       off-axis (std, mrad) errors of gyro and accelerometer
The effects are drawn from --seed; rendering costs one scene render per sub-frame (a blurred
fast frame ~0.5 s, see BENCHMARKS.md).

Deterministic: the same options and --seed give bit-identical files. --seed drives the noise;
the scene (textures, boxes) is fixed by --scene-seed.

examples:
  slam synth room.mcap                                    # figure8, 40 s
  slam synth loop.mcap --profile loop --seed 3
  slam synth fast.mcap --profile aggressive --duration 20 --no-imu-noise
  slam synth biased.mcap --gyro-bias 0.002,-0.001,0.003 --accel-bias 0.05,0.02,-0.04
  slam synth lost.mcap --blackout 10:2                    # frames black from 10 s to 12 s
  slam synth real.mcap --profile aggressive --camera realistic
  slam synth late.mcap --camera realistic --time-offset 15 --calib-rotation-error 0,2,0
  slam synth blur.mcap --exposure 8 --line-delay 30       # blur + rolling shutter only
  slam synth dense.mcap --duration 10 --depth-dir dense_depth --mesh scene.ply
  slam synth v101.mcap --from-trajectory groundtruth_openvins/V1_01_easy.txt \\
      --imu-csv mav0/imu0/data.csv [--imu-csv-on-trajectory]
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


def parse_numbers(text: str | None, option: str, count: int) -> tuple[float, ...] | None:
    """``A,B,...`` -> ``count`` floats."""
    if text is None:
        return None
    try:
        values = tuple(float(v) for v in text.split(","))
    except ValueError as exc:
        raise InputError(f"{option} expects {count} comma-separated numbers, got {text!r}") from exc
    if len(values) != count:
        raise InputError(f"{option} expects {count} comma-separated numbers, got {text!r}")
    return values


def effects_from_args(args: argparse.Namespace) -> tuple[CameraEffects, ImuEffects]:
    """The --camera bundle with each individual option applied over it."""
    from datasets.synth.camera_model import rig_effects

    cam, imu = rig_effects(args.camera)
    cam_changes: dict[str, object] = {}
    if args.exposure is not None:
        cam_changes["exposure_s"] = args.exposure * 1e-3
    if args.auto_exposure:
        cam_changes["auto_exposure"] = True
    if args.illumination is not None:
        cam_changes["illumination_log_amplitude"] = args.illumination
    if args.vignetting is not None:
        cam_changes["vignetting"] = args.vignetting
    if args.stereo_gain is not None:
        cam_changes["stereo_gain"] = args.stereo_gain
    if args.read_noise is not None:
        cam_changes["read_noise_std"] = args.read_noise
    if args.shot_noise is not None:
        cam_changes["shot_noise_gl"] = args.shot_noise
    if args.line_delay is not None:
        cam_changes["line_delay_s"] = args.line_delay * 1e-6
    imu_changes: dict[str, object] = {}
    vib = parse_numbers(args.imu_vibration, "--imu-vibration", 3)
    if vib is not None:
        imu_changes.update(
            vibration_accel_rms_m_s2=vib[0], vibration_gyro_rms_rad_s=vib[1], vibration_hz=vib[2]
        )
    if args.imu_scale_error is not None:
        imu_changes["scale_error_std"] = args.imu_scale_error
    if args.imu_misalignment is not None:
        imu_changes["misalignment_std_rad"] = args.imu_misalignment * 1e-3
    return cam.replace(**cam_changes), dataclasses.replace(imu, **imu_changes)  # type: ignore[arg-type]


def run(args: argparse.Namespace) -> int:
    from datasets.synth.export import run_synth

    camera, imu_effects = effects_from_args(args)
    rot_err = parse_numbers(args.calib_rotation_error, "--calib-rotation-error", 3)

    result = run_synth(
        args.out,
        profile=args.profile,
        duration_s=args.duration,
        seed=args.seed,
        scene_seed=args.scene_seed,
        trajectory_file=args.from_trajectory,
        imu_csv=args.imu_csv,
        imu_csv_on_trajectory=args.imu_csv_on_trajectory,
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
        camera=camera,
        imu_effects=imu_effects,
        time_offset_ns=round(args.time_offset * 1e6),
        calib_rotation_error_deg=None if rot_err is None else (rot_err[0], rot_err[1], rot_err[2]),
    )
    print(
        f"wrote {result.mcap_path}: {result.num_frames} stereo frames, {result.num_imu} IMU "
        f"samples, {result.duration_s:.1f} s, path {result.path_length_m:.1f} m"
    )
    agree = result.gyro_agreement
    if agree is not None:
        print(
            f"real IMU against the trajectory: the gyro over {agree.window_s:g} s windows is "
            f"{agree.median_deg:.2f} deg (median; {agree.max_deg:.2f} max) off its rotation"
        )
    accel = result.accel_scale
    if accel is not None:
        print(
            f"real IMU against the trajectory: accelerations x{accel.scale:.4f} give the "
            f"trajectory's ({accel.rms_residual_m * 1e3:.1f} mm rms left over "
            f"{accel.count} second differences)"
        )
    if result.depth_images:
        print(f"wrote {result.depth_images} depth images (uint16 mm) to {args.depth_dir}")
    if result.mesh_path is not None:
        print(f"wrote scene mesh {result.mesh_path}")
    return 0


def register(subparsers: argparse._SubParsersAction) -> None:
    from datasets.synth.camera_model import CAMERA_BUNDLES

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
    p.add_argument(
        "--imu-csv-on-trajectory",
        action="store_true",
        help="with --imu-csv: the trajectory's exact readings plus the real IMU's bias drift "
        "(< 0.1 Hz) and noise (> 5 Hz), so that its scale agrees with the images",
    )
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
    g = p.add_argument_group("camera and rig effects (see above)")
    g.add_argument("--camera", choices=CAMERA_BUNDLES, default="clean", help="effects bundle")
    g.add_argument("--exposure", type=float, metavar="MS", help="fixed exposure (motion blur)")
    g.add_argument("--auto-exposure", action="store_true", help="auto-exposure with gain steps")
    g.add_argument("--illumination", type=float, metavar="A", help="illumination log amplitude")
    g.add_argument("--vignetting", type=float, metavar="F", help="corner darkening, 0..0.9")
    g.add_argument("--stereo-gain", type=float, metavar="R", help="right/left gain ratio")
    g.add_argument("--read-noise", type=float, metavar="SIGMA", help="grey levels at gain 1")
    g.add_argument("--shot-noise", type=float, metavar="GL", help="grey levels per electron")
    g.add_argument("--line-delay", type=float, metavar="US", help="rolling shutter row delay")
    g.add_argument(
        "--time-offset", type=float, default=0.0, metavar="MS", help="camera-IMU time offset"
    )
    g.add_argument(
        "--calib-rotation-error", metavar="X,Y,Z", help="wrong camera-IMU rotation (deg)"
    )
    g.add_argument("--imu-vibration", metavar="ACC,GYRO,HZ", help="IMU vibration RMS and Hz")
    g.add_argument("--imu-scale-error", type=float, metavar="F", help="IMU scale error std")
    g.add_argument("--imu-misalignment", type=float, metavar="MRAD", help="IMU axis error std")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress bars")
    p.set_defaults(func=run)

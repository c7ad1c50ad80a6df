"""`slam run`: track a sequence and write its trajectory, keyframes, stats and config."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any

from slam.core.errors import SlamError

EPILOG = """\
examples:
  slam run room.mcap --out run1                       # real time (sensor rate), no viewer
  slam run room.mcap --out run1 --speed max --rerun save:run1.rrd
  slam run ~/data/V1_01_easy --out v101 --rerun spawn # an EuRoC folder, live viewer window
  slam run room.mcap --out run1 --rerun serve --keep-viewer
                                  # web viewer on this machine (prints its URL), kept after
  slam run bag.mcap --left-topic /left --right-topic /right --imu-topic /imu \\
           --camchain camchain.yaml --imu-yaml imu.yaml --out run2
  slam run room.mcap --out run1 --sequential          # one thread, deterministic output
  slam run room.mcap --config euroc-mono-imu --out m1 # cam0 + IMU only (monocular-inertial;
                                  # the default for a source with one camera and an IMU)

Ctrl-C (or SIGTERM) stops reading, ends every stage and writes every output for what was
processed (exit code 130 / 143); a second Ctrl-C stops waiting for the stages.
exit codes: 0 done, 1 a stage failed or no frame could be tracked, 2 bad input or
configuration, 3 a worker process died (killed, out of memory), 130 / 143 stopped.

outputs in --out DIR (written atomically, also after Ctrl-C or a failure):
  trajectory.tum   every tracked frame, world_from_body (body = IMU), TUM seconds
  trajectory.csv   the same in the EuRoC ground-truth csv layout
  keyframes.tum    keyframe poses
  stats.json       frames in/tracked/dropped, tracking losses, real-time factor of the
                   tracking and the end-of-run time beside it, per-stage latency
                   p50/p90/p99/max, peak memory of the whole process tree
  config.yaml      the resolved configuration (reusable with --config)
  trajectory_loop_closed.tum   with loop closure on: every frame through its keyframe's
                   pose-graph correction
  mesh.ply         with --mesh: the dense mesh (binary PLY: MeshLab, Open3D)

then score it:  slam eval ape SEQ DIR --align se3
"""


def register(sub: argparse._SubParsersAction) -> None:
    from slam.config import PRESETS
    from slam.runtime.viewer import RERUN_MODES
    from tools.seq_args import SEQUENCE_HELP, add_sequence_args

    p = sub.add_parser(
        "run",
        help="track a sequence (trajectory, keyframes, stats) with optional live rerun view",
        description="Run the SLAM pipeline on a sequence SEQ.\n\n"
        + SEQUENCE_HELP
        + "\nThe configuration is a preset or a YAML file (--config); every key with its "
        "default,\nunit and what it does: slam config show [PRESET]",
        epilog=EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )

    add_sequence_args(p)
    p.add_argument("--out", required=True, type=Path, help="output folder (created)")
    p.add_argument(
        "--config",
        default=None,
        metavar="PRESET|FILE",
        help=f"a preset ({', '.join(sorted(PRESETS))}) or a YAML file; "
        "default: the stereo-inertial preset when the sequence has IMU, else stereo-vo; "
        "every key: slam config show [PRESET]",
    )
    p.add_argument(
        "--rerun",
        default="none",
        metavar="MODE",
        help=f"viewer ({RERUN_MODES}): spawn = a viewer window (without a display the run "
        "records to OUT/recording.rrd instead); save:FILE.rrd = a recording; serve = a web "
        "viewer on this machine only (127.0.0.1, the URL is printed; serve:0.0.0.0 exposes it "
        "to the network); connect:URL = a running viewer; none (default). The viewer never "
        "slows the run down: it drops what it cannot take.",
    )
    p.add_argument(
        "--speed",
        default=None,
        help="playback speed: 1 = sensor rate (default), 4 = four times faster, "
        "max = as fast as the pipeline takes it",
    )
    p.add_argument(
        "--sequential",
        action="store_true",
        help="run every stage in one thread in time order (deterministic, for debugging)",
    )
    p.add_argument("--max-frames", type=int, default=None, help="stop after N frames")
    p.add_argument(
        "--mesh",
        action="store_true",
        help="dense mapping (plane sweep + TSDF in a worker process): writes mesh.ply and "
        "shows the mesh in rerun",
    )
    p.add_argument(
        "--keep-viewer",
        action="store_true",
        help="with --rerun serve: keep serving the final map after the run until Ctrl-C",
    )
    p.add_argument(
        "--strict",
        action="store_true",
        help="refuse a sequence that would lose frames (a listed image file missing, a "
        "truncated file, a corrupt chunk); by default they are skipped with a warning",
    )
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.set_defaults(func=handle)


def parse_speed(text: str) -> float:
    if text == "max":
        return 0.0
    try:
        value = float(text)
    except ValueError:
        raise SlamError(f"--speed must be a number or 'max', got {text!r}") from None
    if value <= 0:
        raise SlamError("--speed must be positive (or 'max')")
    return value


def handle(args: argparse.Namespace) -> int:
    from datasets.open import open_sequence
    from slam.config import check_run_config, load_config, validate_config
    from tools.seq_args import source_options

    out: Path = args.out
    if out.exists() and not out.is_dir():
        raise SlamError(f"--out {out} exists and is not a folder; give a folder for the outputs")
    # the input is opened and the configuration checked before --out is made: a bad input or
    # configuration leaves nothing behind
    seq = open_sequence(args.seq, **source_options(args), strict=args.strict)
    if not seq.calibration.is_stereo and seq.num_imu:
        default_preset = "euroc-mono-imu"  # one camera: cam0 + IMU
    else:
        default_preset = "euroc-stereo-imu" if seq.num_imu else "stereo-vo"
    cfg = load_config(args.config, default_preset)
    if args.speed is not None:
        cfg.player.speed = parse_speed(args.speed)
    if args.sequential:
        cfg.player.sequential = True
    if args.max_frames is not None:
        cfg.player.max_frames = args.max_frames
    if args.mesh:
        import dataclasses

        cfg.mapping = dataclasses.replace(cfg.mapping, enabled=True)
    validate_config(cfg)  # with the command line's overrides
    check_run_config(cfg, seq.name, stereo=seq.calibration.is_stereo, has_imu=seq.has_imu)
    try:  # fail before the run, not after it, when the folder cannot be made
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise SlamError(f"--out {out}: cannot create the output folder ({exc.strerror})") from None
    from slam.runtime.wiring import run_slam  # heavy (OpenCV, GTSAM): once the inputs are fine

    result = run_slam(
        seq,
        cfg,
        args.out,
        args.rerun,
        progress=not args.no_progress,
        keep_viewer=args.keep_viewer,
    )
    print_summary(result.stats, args.out)
    code = exit_code(result)
    if result.session is not None and result.session.web_url and args.keep_viewer and code == 0:
        print(f"rerun web viewer still serving the run at {result.session.web_url}; Ctrl-C to stop")
        try:
            result.session.server_wait()
        except KeyboardInterrupt:
            pass
    if result.session is not None:
        result.session.stop_server()
    return code


def print_summary(s: dict, out: Path) -> None:
    """The run's figures in a few lines (the same numbers as stats.json)."""
    fe = s["latency"]["frontend_frame"]
    end = s.get("end_of_run_s")
    parts = ", ".join(f"{k} {v:.1f} s" for k, v in (s.get("end_of_run_parts_s") or {}).items())
    print(
        f"{s['frames_tracked']}/{s['frames_in']} frames tracked, {s['frames_dropped']} dropped, "
        f"{s['tracking_losses']} tracking losses, {s['keyframes']} keyframes"
    )
    print(
        f"tracking: real-time factor {s['real_time_factor']:.2f} "
        f"({s['sequence_duration_s']:.1f} s of sequence in {s['tracking_wall_s']:.1f} s); "
        f"front end p50 {fe.get('p50_ms', 0):.1f} ms p99 {fe.get('p99_ms', 0):.1f} ms"
    )
    if end is not None:
        print(f"end of run: {end:.1f} s" + (f" ({parts})" if parts else ""))
    loop = s.get("loop_closure") or {}
    if loop.get("global_ba_skipped"):
        print(f"global adjustment: {loop['global_ba_skipped']} (the pose graph's result is kept)")
    elif (loop.get("global_ba") or {}).get("time_boxed"):
        print("global adjustment: time-boxed (its estimate when its time budget ran out)")
    print(f"peak memory of the process tree: {s['peak_rss_mb']:.0f} MB")
    print(f"outputs in {out}/ (trajectory.tum, trajectory.csv, keyframes.tum, stats.json)")
    frames = max(s["frames_in"], 1)
    if 0 < s["frames_tracked"] < 0.5 * frames:
        print(
            f"WARNING: only {s['frames_tracked']} of {s['frames_in']} frames were tracked "
            f"({100 * s['frames_tracked'] / frames:.0f} %): the trajectory covers less than half "
            "of the sequence (see the events in stats.json)",
            file=sys.stderr,
        )


EXIT_WORKER_DIED = 3


def exit_code(result: Any) -> int:
    """0; 1 for a stage failure or a run that tracked nothing; 3 when a worker process died;
    128 + signal when stopped."""
    if result.error is not None:
        from slam.runtime.worker import WorkerDied

        print(
            f"slam run: error: {result.error} (outputs saved for what was processed)",
            file=sys.stderr,
        )
        return EXIT_WORKER_DIED if isinstance(result.error.exc, WorkerDied) else 1
    if result.interrupted:
        print(
            f"slam run: stopped by {result.stats.get('stopped_by') or 'SIGINT'}; outputs saved "
            "for what was processed",
            file=sys.stderr,
        )
        return result.exit_code or 130
    s = result.stats
    waiting = s.get("frame_states", {}).get("waiting for motion", 0)
    if s["frames_in"] > 0 and s["frames_tracked"] == 0 and waiting >= 0.5 * s["frames_in"]:
        print(
            f"slam run: error: waiting for motion: {waiting} of {s['frames_in']} frames, the "
            "camera hardly moved; a monocular run needs motion to find the scale (no pose given)",
            file=sys.stderr,
        )
        return 1
    if s["frames_in"] > 0 and s["frames_tracked"] == 0:
        print(
            f"slam run: error: none of the {s['frames_in']} frames could be tracked (see the "
            "events in stats.json: black or textureless images, a wrong calibration?)",
            file=sys.stderr,
        )
        return 1
    return 0

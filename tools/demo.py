"""`make demo`: the whole system on a built-in default, from nothing.

Generates a synthetic stereo-inertial sequence with exact ground truth, summarises it, tracks it
with the stereo-inertial preset and a dense mesh (recording a rerun file), and scores the
trajectory against the ground truth. Each step is the same `slam` command a user would type;
they are printed first. The end names only files that were written (else the demo fails) and
how to look at the recording, with or without a display.
"""

from __future__ import annotations

import argparse
import os
import shlex
import shutil
import sys
import time
from pathlib import Path

from tools.cli import main as slam_main


def _step(title: str, argv: list[str]) -> None:
    print(f"\n=== {title}\n$ slam {shlex.join(argv)}", flush=True)
    t0 = time.perf_counter()
    code = slam_main(argv)
    if code != 0:
        print(f"demo: step failed with exit code {code}", file=sys.stderr)
        sys.exit(code)
    print(f"({time.perf_counter() - t0:.1f} s)", flush=True)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--out", type=Path, default=Path("demo_out"), help="output folder")
    parser.add_argument("--profile", default="figure8", help="synthetic trajectory profile")
    parser.add_argument("--duration", default="30", help="sequence length, seconds")
    args = parser.parse_args(argv)
    out: Path = args.out
    out.mkdir(parents=True, exist_ok=True)
    seq = out / f"{args.profile}.mcap"
    run = out / "run"
    if not seq.exists():
        _step(
            "1. generate a synthetic sequence (stereo 752x480 @ 20 Hz, IMU @ 200 Hz, ground truth)",
            ["synth", str(seq), "--profile", args.profile, "--duration", args.duration],
        )
    else:
        print(f"\n=== 1. reusing {seq} (delete it to regenerate)")
    _step("2. what is in it", ["info", str(seq)])
    _step(
        "3. track it: stereo-inertial front end + GTSAM back end + dense mesh, rerun recording "
        "saved",
        [
            "run",
            str(seq),
            "--out",
            str(run),
            "--speed",
            "max",
            "--mesh",
            "--rerun",
            f"save:{out / 'run.rrd'}",
        ],
    )
    _step(
        "4. score it against the ground truth (se3 alignment; plot in ape.png)",
        [
            "eval",
            "ape",
            str(seq),
            str(run),
            "--align",
            "se3",
            "--plot",
            str(out / "ape.png"),
            "--json",
            str(out / "ape.json"),
        ],
    )
    rrd = out / "run.rrd"
    outputs = {
        "trajectory": run / "trajectory.tum",
        "loop_closed": run / "trajectory_loop_closed.tum",
        "mesh": run / "mesh.ply",
        "plot": out / "ape.png",
        "recording": rrd,
    }
    missing = [str(p) for p in outputs.values() if not p.is_file() or p.stat().st_size == 0]
    if missing:
        print(f"demo: not written (or empty): {', '.join(missing)}", file=sys.stderr)
        return 1
    print(summary(outputs, rerun_command(), _has_display()))
    return 0


def _has_display() -> bool:
    from slam.runtime.viewer import has_display

    return has_display()


def rerun_command() -> str:
    """How to call the rerun viewer installed with this Python (``.venv/bin/rerun`` after `make
    demo`), relative to the current folder when it is inside it."""
    exe = shutil.which("rerun", path=str(Path(sys.executable).parent)) or "rerun"
    if os.path.isabs(exe) and Path(exe).is_relative_to(Path.cwd()):
        exe = os.path.relpath(exe)
    return exe


def summary(outputs: dict[str, Path], rerun: str, display: bool) -> str:
    """The demo's last words: what it wrote and how to look at the recording."""
    rrd = outputs["recording"]
    web = f"{rerun} {rrd} --web-viewer --bind 127.0.0.1"
    window = f"`{rerun} {rrd}` opens it in a window; without a display, " if display else ""
    return (
        f"\nDone. Trajectory: {outputs['trajectory']} (loop-closed: "
        f"{outputs['loop_closed'].name}); dense mesh: {outputs['mesh']} (MeshLab, Open3D); "
        f"error plot: {outputs['plot']}.\n"
        f"Look at the recording: {window}`{web}` serves it on this machine only and prints a "
        "http://127.0.0.1:... address to open in a browser (Ctrl-C ends it)."
    )


if __name__ == "__main__":
    sys.exit(main())

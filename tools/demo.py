"""`make demo`: the whole system on a built-in default, from nothing.

Generates a synthetic stereo-inertial sequence with exact ground truth, summarises it, tracks it
with the stereo-inertial preset (recording a rerun file), and scores the trajectory against the
ground truth. Each step is the same `slam` command a user would type; they are printed first.
"""

from __future__ import annotations

import argparse
import shlex
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
        "3. track it: stereo-inertial front end + GTSAM back end, rerun recording saved",
        [
            "run",
            str(seq),
            "--out",
            str(run),
            "--speed",
            "max",
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
    print(
        f"\nDone. The trajectory is in {run}/trajectory.tum (loop-closed: "
        f"trajectory_loop_closed.tum), the error plot in {out / 'ape.png'}.\n"
        f"Look at the recording: `.venv/bin/rerun {rrd}` (a window), or without a display "
        f"`.venv/bin/rerun {rrd} --web-viewer --bind 127.0.0.1` and open the printed "
        "http://127.0.0.1:9090 address in a browser."
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())

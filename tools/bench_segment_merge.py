"""Benchmark: a tracking loss that relocalisation cannot bridge, then a merge by loop closure.

Stereo only (no IMU to dead-reckon across the gap), loop closure on: a synthetic loop with a
long blackout early in the first lap, so that tracking resumes where nothing has been mapped
yet. The front end starts a second map segment (its own, unrelated frame); when the second lap
revisits the start, verified loops between the segments merge them. The online trajectory holds
the two frames side by side (a large ATE under one alignment); the loop-closed one should be one
consistent trajectory.

    .venv/bin/python -m tools.bench_segment_merge [--duration 110] [--blackout 10:5] [--out DIR]

Sequential mode (deterministic); a few minutes on 2 cores for the default 110 s.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from slam.config import load_config
from slam.evaluation.io import write_tum


def main(argv: list[str] | None = None) -> int:
    from datasets.synth import make_synthetic_sequence
    from slam.runtime.wiring import run_slam
    from tools.cli import main as slam_main

    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--duration", type=float, default=110.0, help="seconds (two laps: 110)")
    parser.add_argument("--blackout", default="10:5", help="START_S:DURATION_S of black frames")
    parser.add_argument("--out", type=Path, default=Path("/tmp/bench_segment_merge"))
    args = parser.parse_args(argv)
    start_s, length_s = (float(x) for x in args.blackout.split(":"))
    seq = make_synthetic_sequence(
        profile="loop", duration_s=args.duration, seed=4, blackout=(start_s, length_s)
    )
    cfg = load_config("stereo-vo")
    cfg.loop_closure = True
    cfg.player.sequential = True
    cfg.player.speed = 0.0  # as fast as it goes (sequential: deterministic)
    assert seq.ground_truth is not None  # synthetic sequences always carry it
    result = run_slam(seq, cfg, args.out, progress=True)
    write_tum(args.out / "groundtruth.tum", seq.ground_truth)
    stats = result.stats
    loops = stats["loop_closure"]["loops"]
    print(
        f"map segments {stats['map_segments']}, relocalisations {stats['relocalisations']}, "
        f"loops accepted {len(loops)}"
    )
    out: dict[str, object] = {"map_segments": stats["map_segments"], "loops": len(loops)}
    for name in ("trajectory", "trajectory_loop_closed"):
        report = args.out / f"ape_{name}.json"
        slam_main(
            [
                "eval",
                "ape",
                str(args.out / "groundtruth.tum"),
                str(args.out / f"{name}.tum"),
                "--json",
                str(report),
            ]
        )
        out[f"ape_{name}"] = json.loads(report.read_text())["stats"]
    (args.out / "bench_segment_merge.json").write_text(json.dumps(out, indent=2, default=str))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

"""Memory over a long run: peak RSS of the pipeline (main process + worker processes) over time.

Runs `run_slam` at --speed max on a long synthetic sequence rendered on the fly (a 20-minute
sequence never lives in memory or on disk) and samples the resident set size of this process
and of every worker process once per second. Prints RSS at 2 minutes and at the end (sensor
time), and writes the samples as JSON.

    python -m tools.bench_memory --minutes 20 --profile hall --out memory.json
"""

from __future__ import annotations

import argparse
import json
import multiprocessing as mp
import os
import threading
import time
from pathlib import Path


def rss_mb(pid: int) -> float:
    try:
        with open(f"/proc/{pid}/status") as f:
            for line in f:
                if line.startswith("VmRSS:"):
                    return int(line.split()[1]) / 1024.0
    except OSError:
        pass
    return 0.0


def main(argv: list[str] | None = None) -> int:
    from datasets.synth import make_synthetic_sequence
    from slam.config import load_config
    from slam.runtime.wiring import run_slam

    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--minutes", type=float, default=20.0)
    parser.add_argument("--profile", default="hall")
    parser.add_argument("--config", default="euroc-stereo-imu")
    parser.add_argument("--out", type=Path, default=Path("memory.json"))
    args = parser.parse_args(argv)

    seq = make_synthetic_sequence(profile=args.profile, duration_s=args.minutes * 60.0, seed=7)
    cfg = load_config(args.config)
    cfg.player.speed = 0.0
    samples: list[dict[str, float]] = []
    stop = threading.Event()
    t0 = time.perf_counter()

    def sampler() -> None:
        while not stop.wait(1.0):
            children = {p.name: rss_mb(p.pid) for p in mp.active_children() if p.pid}
            samples.append(
                {
                    "wall_s": time.perf_counter() - t0,
                    "main_mb": rss_mb(os.getpid()),
                    "children_mb": sum(children.values()),
                    **{f"{k}_mb": v for k, v in children.items()},
                }
            )

    thread = threading.Thread(target=sampler, daemon=True)
    thread.start()
    result = run_slam(seq, cfg, None, progress=True)
    stop.set()
    thread.join()
    wall = time.perf_counter() - t0
    # wall time -> sensor time (linear: the run goes at a roughly constant rate)
    duration_s = seq.duration_ns * 1e-9
    for s in samples:
        s["sensor_s"] = s["wall_s"] / wall * duration_s

    def at(sensor_s: float) -> dict[str, float]:
        before = [s for s in samples if s["sensor_s"] <= sensor_s]
        return {
            "peak_main_mb": max((s["main_mb"] for s in before), default=0.0),
            "peak_total_mb": max((s["main_mb"] + s["children_mb"] for s in before), default=0.0),
        }

    report = {
        "profile": args.profile,
        "minutes": args.minutes,
        "config": args.config,
        "frames_tracked": result.stats["frames_tracked"],
        "frames_in": result.stats["frames_in"],
        "at_2_min": at(120.0),
        "at_end": at(duration_s),
        "samples": samples,
    }
    args.out.write_text(json.dumps(report, indent=1))
    print(f"peak RSS at 2 min: {report['at_2_min']}")
    print(f"peak RSS at {args.minutes:g} min: {report['at_end']}")
    print(f"tracked {report['frames_tracked']}/{report['frames_in']} frames; samples in {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

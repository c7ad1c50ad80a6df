"""A run on a busy machine: the suite beside unrelated normal-priority busy processes.

A robot's computer is never idle. Each condition runs every suite sequence in its own
`slam run` process (stereo-inertial preset, loop closure on, no viewer) while ``--busy`` other
processes spin at normal priority, one per core by default:

- ``idle-rt``: ``--speed 1`` on an otherwise idle machine (the reference for live ATE);
- ``busy2-rt``: ``--speed 1`` beside two busy processes;
- ``busy1-max``: ``--speed max`` beside one busy process.

Per run: the tracking's wall time (start of playback to the last frame answered) and the whole
process's (start-up and end-of-run work included) over the sequence's duration, frames dropped, the back end's update p99, the real-time factor of tracking, the live
(causal) ATE and its ratio to the idle real-time run's, and the loop-closed ATE.

    python -m tools.bench_load --out bench_load            # the whole suite (~15 min)
    python -m tools.bench_load --out bl --quick 30 --conditions busy2-rt
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

from slam.core.atomic import write_atomic
from tools.batch.measure import ate_se3
from tools.benchmark import (
    STANDARD_SUITE,
    default_cache_dir,
    ensure_sequence,
    quick_suite,
    run_one,
)

CONDITIONS: dict[str, tuple[int, str]] = {
    "idle-rt": (0, "1"),
    "busy2-rt": (2, "1"),
    "busy1-max": (1, "max"),
}
"""Condition -> (busy processes, --speed)."""

SPIN = "import os\nparent = os.getppid()\nwhile os.getppid() == parent:\n    for _ in range(200_000):\n        pass\n"
"""A busy loop that ends when this tool does (re-parented: the tool was killed, even by SIGKILL,
which skips ``stop_busy``; left spinning, they skewed every later measurement)."""


def start_busy(n: int) -> list[subprocess.Popen[bytes]]:
    """``n`` processes that keep a core busy each, at the normal priority."""
    return [subprocess.Popen([sys.executable, "-c", SPIN]) for _ in range(n)]


def stop_busy(procs: list[subprocess.Popen[bytes]]) -> None:
    for p in procs:
        p.terminate()
    for p in procs:
        p.wait(timeout=10)


def run_condition(name: str, seq_path: Path, out_dir: Path, preset: str | None) -> dict[str, Any]:
    busy, speed = CONDITIONS[name]
    procs = start_busy(busy)
    try:
        time.sleep(0.5 if busy else 0.0)
        stats = run_one(seq_path, out_dir, preset, [], speed=speed)
    finally:
        stop_busy(procs)
    be = (stats.get("backend") or {}).get("update") or {}
    fe = stats["latency"]["frontend_frame"]
    frames_in = max(stats["frames_in"], 1)
    seq_s = max(stats["sequence_duration_s"], 1e-9)
    return {
        "condition": name,
        "sequence": seq_path.name.split("-v")[0],
        "wall_over_duration": stats["process_wall_s"] / seq_s,
        "tracking_over_duration": stats["tracking_wall_s"] / seq_s,
        "dropped_pct": 100.0 * stats["frames_dropped"] / frames_in,
        "backend_p99_ms": be.get("p99_ms"),
        "backend_max_ms": be.get("max_ms"),
        "real_time_factor": stats["real_time_factor"],
        "end_of_run_s": stats.get("end_of_run_s"),
        "frontend_p99_ms": fe.get("p99_ms"),
        "completion_pct": 100.0 * stats["frames_tracked"] / frames_in,
        "ate_live_m": ate_se3(seq_path, out_dir / "trajectory.tum"),
        "ate_loop_closed_m": ate_se3(seq_path, out_dir / "trajectory_loop_closed.tum"),
    }


COLUMNS = (
    ("condition", "condition", "{}"),
    ("sequence", "sequence", "{}"),
    ("tracking_over_duration", "tracking / duration", "{:.2f}"),
    ("wall_over_duration", "process / duration", "{:.2f}"),
    ("dropped_pct", "dropped (%)", "{:.1f}"),
    ("backend_p99_ms", "BE p99 (ms)", "{:.0f}"),
    ("backend_max_ms", "BE max (ms)", "{:.0f}"),
    ("real_time_factor", "RTF", "{:.2f}"),
    ("end_of_run_s", "end (s)", "{:.1f}"),
    ("frontend_p99_ms", "FE p99 (ms)", "{:.1f}"),
    ("completion_pct", "completion (%)", "{:.1f}"),
    ("ate_live_m", "ATE live (m)", "{:.4f}"),
    ("live_vs_idle", "live / idle-rt", "{:.2f}"),
    ("ate_loop_closed_m", "ATE loop-closed (m)", "{:.4f}"),
)


def table(rows: list[dict[str, Any]]) -> str:
    lines = [
        "| " + " | ".join(t for _, t, _ in COLUMNS) + " |",
        "|" + "|".join("---" for _ in COLUMNS) + "|",
    ]
    for r in rows:
        cells = []
        for key, _, fmt in COLUMNS:
            v = r.get(key)
            cells.append("-" if v is None else fmt.format(v))
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--quick", type=float, default=None, metavar="S", help="cut sequences to S s")
    ap.add_argument(
        "--conditions",
        nargs="+",
        default=list(CONDITIONS),
        choices=list(CONDITIONS),
        help="which conditions to run (default: all)",
    )
    ap.add_argument("--only", nargs="+", default=None, metavar="NAME", help="suite sequences")
    ap.add_argument("--config", default=None, help="preset or YAML for every run")
    ap.add_argument("--cache-dir", type=Path, default=None)
    args = ap.parse_args(argv)
    suite = quick_suite(args.quick) if args.quick else STANDARD_SUITE
    cache = args.cache_dir or default_cache_dir()
    rows: list[dict[str, Any]] = []
    idle_ate: dict[str, float] = {}
    for entry in suite:
        if args.only and entry.name not in args.only:
            continue
        seq_path = ensure_sequence(entry, cache)
        for cond in args.conditions:
            out = args.out / cond / entry.name
            print(f"{cond}: {entry.name} ...", flush=True)
            row = run_condition(cond, seq_path, out, args.config)
            row["sequence"] = entry.name
            if cond == "idle-rt" and row["ate_live_m"]:
                idle_ate[entry.name] = row["ate_live_m"]
            ref = idle_ate.get(entry.name)
            row["live_vs_idle"] = (
                None if not ref or not row["ate_live_m"] else row["ate_live_m"] / ref
            )
            rows.append(row)
            args.out.mkdir(parents=True, exist_ok=True)
            write_atomic(args.out / "results.json", json.dumps(rows, indent=2) + "\n")
            write_atomic(args.out / "results.md", table(rows))
    print(table(rows))
    print(f"machine: {os.cpu_count()} CPUs; results in {args.out}/results.md")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

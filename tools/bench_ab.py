"""Is B faster (or more accurate) than A? Two versions of the code, interleaved in one window.

This machine's speed drifts by the hour (the same code's front-end CPU p99 moved by a third
between two sessions), so a speed figure means something only against another measured in the
same window. This tool runs `slam run` (one process per run, no viewer) alternately with two
versions of the code, A then B then B then A and so on, on the same suite sequences, and
reports each run and the medians side by side, with B / A.

A version is a git commit (exported with ``git archive`` into ``OUT/tree-a``) or a folder with
the project's source (a worktree); both run with this interpreter's packages, so their
dependencies must match. Per run: real-time factor, front-end latency p99 (and its CPU time,
run-queue wait), the machine's stolen share, end of run, live and loop-closed ATE.

    python -m tools.bench_ab --a caf65f1 --out /tmp/ab                  # caf65f1 vs this tree
    python -m tools.bench_ab --a main --b /work/wt/branch --only hall --repeats 3 --out /tmp/ab
    python -m tools.bench_ab --a HEAD~1 --speed 1 --only room-loop --run-arg=--mesh --out /tmp/ab
"""

from __future__ import annotations

import argparse
import io
import json
import subprocess
import tarfile
from pathlib import Path
from typing import Any

from slam.core.atomic import write_atomic
from slam.core.errors import SlamError
from tools.batch.measure import ate_se3
from tools.benchmark import STANDARD_SUITE, default_cache_dir, ensure_sequence, median, run_one

REPO = Path(__file__).resolve().parent.parent

METRICS: tuple[tuple[str, str, str], ...] = (
    ("real_time_factor", "RTF", "{:.2f}"),
    ("frontend_p99_ms", "FE p99 ms", "{:.1f}"),
    ("frontend_cpu_p99_ms", "FE CPU p99 ms", "{:.1f}"),
    ("frontend_runqueue_p99_ms", "FE run-queue p99 ms", "{:.1f}"),
    ("steal_pct", "steal %", "{:.1f}"),
    ("end_of_run_s", "end s", "{:.1f}"),
    ("ate_live_mm", "ATE live mm", "{:.3f}"),
    ("ate_loop_closed_mm", "ATE loop-closed mm", "{:.3f}"),
)
"""Per run: key, column title, format."""


def source_tree(version: str, out: Path, label: str) -> Path:
    """The source folder of ``version``: a folder as it is, or a git commit exported (tracked
    files only) into ``out/tree-<label>``."""
    path = Path(version)
    if path.is_dir():
        if not (path / "tools" / "cli.py").is_file():
            raise SlamError(f"{version} is not a source tree of this project (no tools/cli.py)")
        return path.resolve()
    proc = subprocess.run(
        ["git", "-C", str(REPO), "archive", "--format=tar", version],
        capture_output=True,
    )
    if proc.returncode != 0:
        msg = proc.stderr.decode(errors="replace").strip().splitlines()
        raise SlamError(f"{version}: neither a folder nor a git commit ({' '.join(msg[-1:])})")
    dest = out / f"tree-{label}"
    dest.mkdir(parents=True, exist_ok=True)
    with tarfile.open(fileobj=io.BytesIO(proc.stdout)) as tar:
        tar.extractall(dest, filter="data")
    return dest.resolve()


def run_order(repeats: int) -> list[tuple[int, str]]:
    """(repeat, version) in an ABBA order: each version runs first as often as second, so a
    machine that slows down (or speeds up) through the window favours neither."""
    order: list[tuple[int, str]] = []
    for i in range(repeats):
        order += [(i, "a"), (i, "b")] if i % 2 == 0 else [(i, "b"), (i, "a")]
    return order


def run_record(stats: dict[str, Any], seq_path: Path, run_dir: Path) -> dict[str, Any]:
    """The figures of one run, from its stats.json and trajectories."""
    lat = stats.get("latency") or {}

    def p99(name: str) -> float | None:
        value = (lat.get(name) or {}).get("p99_ms")
        return None if value is None else float(value)

    steal = (stats.get("machine_cpu") or {}).get("steal_fraction")
    live = ate_se3(seq_path, run_dir / "trajectory.tum")
    closed = ate_se3(seq_path, run_dir / "trajectory_loop_closed.tum")
    return {
        "real_time_factor": stats.get("real_time_factor"),
        "frontend_p99_ms": p99("frontend_frame"),
        "frontend_cpu_p99_ms": p99("frontend_frame_cpu"),
        "frontend_runqueue_p99_ms": p99("frontend_frame_runqueue"),
        "steal_pct": None if steal is None else 100.0 * steal,
        "end_of_run_s": stats.get("end_of_run_s"),
        "ate_live_mm": None if live is None else 1e3 * live,
        "ate_loop_closed_mm": None if closed is None else 1e3 * closed,
    }


def markdown(records: list[dict[str, Any]], versions: dict[str, str]) -> str:
    """Per sequence and metric: A's runs, B's runs, the medians and B / A."""
    lines = [
        f"A = `{versions['a']}`, B = `{versions['b']}`; runs in the order they ran.",
        "",
        "| sequence | metric | A runs | B runs | A median | B median | B / A |",
        "|---|---|---|---|---|---|---|",
    ]
    for seq in dict.fromkeys(r["sequence"] for r in records):
        rows = {v: [r for r in records if r["sequence"] == seq and r["version"] == v] for v in "ab"}
        for key, title, form in METRICS:
            runs = {
                v: " / ".join("-" if r.get(key) is None else form.format(r[key]) for r in rows[v])
                for v in "ab"
            }
            med = {v: median([r.get(key) for r in rows[v]]) for v in "ab"}
            cells = ["-" if med[v] is None else form.format(med[v]) for v in "ab"]
            a_med, b_med = med["a"], med["b"]
            ratio = "-" if not a_med or b_med is None else f"{b_med / a_med:.2f}"
            lines.append(
                f"| {seq} | {title} | {runs['a']} | {runs['b']} | {cells[0]} | {cells[1]} | {ratio} |"
            )
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(
        description=__doc__.split("\n\n")[0],
        epilog=__doc__.split("\n\n", 1)[1],
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    ap.add_argument("--a", required=True, help="version A: a git commit or a source folder")
    ap.add_argument("--b", default=str(REPO), help="version B (default: this source tree)")
    ap.add_argument("--out", type=Path, required=True, help="output folder")
    ap.add_argument(
        "--only",
        nargs="+",
        default=["room-aggressive"],
        metavar="NAME",
        help="suite sequences (default: room-aggressive); 'all' for the whole suite",
    )
    ap.add_argument("--repeats", type=int, default=3, help="runs of each version per sequence")
    ap.add_argument("--speed", default="max", help="slam run --speed (default: max)")
    ap.add_argument("--config", default=None, help="preset or YAML for every run")
    ap.add_argument(
        "--run-arg",
        action="append",
        default=[],
        metavar="ARG",
        help="extra argument for slam run (repeatable), e.g. --run-arg=--mesh",
    )
    args = ap.parse_args(argv)
    if args.repeats < 1:
        ap.error("--repeats must be at least 1")
    names = [e.name for e in STANDARD_SUITE]
    only = names if args.only == ["all"] else args.only
    unknown = sorted(set(only) - set(names))
    if unknown:
        ap.error(f"unknown suite sequence(s) {', '.join(unknown)}; choose from {', '.join(names)}")
    args.out.mkdir(parents=True, exist_ok=True)
    try:
        trees = {"a": source_tree(args.a, args.out, "a"), "b": source_tree(args.b, args.out, "b")}
    except SlamError as exc:
        ap.exit(2, f"bench_ab: {exc}\n")
    versions = {"a": args.a, "b": args.b}
    records: list[dict[str, Any]] = []
    run_args = ["--rerun", "none", *args.run_arg]
    for entry in STANDARD_SUITE:
        if entry.name not in only:
            continue
        seq_path = ensure_sequence(entry, default_cache_dir())
        for i, v in run_order(args.repeats):
            run_dir = args.out / entry.name / f"{v}{i + 1}"
            print(f"{entry.name}: {v.upper()} run {i + 1} ...", flush=True)
            stats = run_one(seq_path, run_dir, args.config, run_args, args.speed, trees[v])
            records.append(
                {"sequence": entry.name, "version": v, "repeat": i + 1}
                | run_record(stats, seq_path, run_dir)
            )
            write_atomic(args.out / "results.json", json.dumps(records, indent=2) + "\n")
            write_atomic(args.out / "results.md", markdown(records, versions))
    print(markdown(records, versions))
    print(f"results in {args.out}/results.md")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

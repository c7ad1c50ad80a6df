"""The project's benchmark: run the pipeline over a suite of sequences and tabulate the results.

The standard suite is synthetic (exact ground truth, EuRoC-grade simulated IMU noise), generated
once per definition and cached as MCAP files (deterministic: same definition, same bytes). Each
run is a separate `slam run` process at ``--speed max`` without a viewer, so peak memory and
timing belong to that run alone. Per run: ATE RMSE (se3 and posyaw), RPE at 1 m and 10 m,
drift (% of distance over sub-trajectories of 10-50 % of the path, rpg style), completion (% of
frames with a pose), initialisation time, real-time factor, front-end latency p50/p99, back-end
update p50/p99, peak RSS.

Loop closure: on suite sequences flagged ``revisits`` (they come back to places seen long
before, after drift has accumulated), a second run of the same sequence with the same resolved
configuration but ``loop_closure: false`` gives "the same run's ATE with loop closure off" and
the ratio loop-closed / off. A separate run, not the online trajectory of the loop-closure run:
that one is also changed by relocalisation against the map. ``--no-loop-baseline`` skips it.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np

from slam.core.errors import SlamError
from slam.core.geometry import rotation_angle_rad

SUITE_VERSION = 1


@dataclass(frozen=True)
class SuiteEntry:
    """One synthetic benchmark sequence."""

    name: str
    profile: str
    duration_s: float
    seed: int
    scale: str  # "room" or "hall": which accuracy target applies
    revisits: bool = True  # comes back to earlier places: also run with loop closure off

    def file_name(self) -> str:
        return (
            f"{self.name}-{self.profile}-{self.duration_s:g}s-seed{self.seed}-v{SUITE_VERSION}.mcap"
        )


STANDARD_SUITE = (
    SuiteEntry("room-figure8", "figure8", 60.0, 1, "room"),
    SuiteEntry("room-loop", "loop", 80.0, 2, "room"),
    SuiteEntry("room-aggressive", "aggressive", 60.0, 3, "room"),
    SuiteEntry("hall", "hall", 140.0, 4, "hall"),
)


def quick_suite(duration_s: float) -> tuple[SuiteEntry, ...]:
    """The standard suite cut to ``duration_s`` per sequence (smoke tests, quick checks)."""
    return tuple(
        SuiteEntry(e.name, e.profile, min(e.duration_s, duration_s), e.seed, e.scale, e.revisits)
        for e in STANDARD_SUITE
    )


def default_cache_dir() -> Path:
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(base) / "pyvislam" / "bench"


def ensure_sequence(entry: SuiteEntry, cache_dir: Path, progress: bool = True) -> Path:
    """The cached MCAP of a suite entry, generated first if missing."""
    from datasets.mcap_io import write_sequence_mcap
    from datasets.synth import make_synthetic_sequence

    path = cache_dir / entry.file_name()
    if path.exists():
        return path
    cache_dir.mkdir(parents=True, exist_ok=True)
    print(f"generating {path.name} (cached for later runs)", flush=True)
    seq = make_synthetic_sequence(
        profile=entry.profile, duration_s=entry.duration_s, seed=entry.seed
    )
    write_sequence_mcap(seq, path, progress=progress)
    return path


def run_one(
    seq_path: Path,
    out_dir: Path,
    preset: str | None,
    extra_args: list[str],
    speed: str = "max",
) -> dict[str, Any]:
    """`slam run` in its own process; returns its stats.json (raises on failure)."""
    cmd = [
        sys.executable,
        "-m",
        "tools.cli",
        "run",
        str(seq_path),
        "--out",
        str(out_dir),
        "--speed",
        speed,
        "--no-progress",
        *extra_args,
    ]
    if preset:
        cmd += ["--config", preset]
    t0 = time.perf_counter()
    proc = subprocess.run(cmd, capture_output=True, text=True)
    wall = time.perf_counter() - t0
    if proc.returncode != 0:
        tail = (proc.stderr or proc.stdout).strip().splitlines()[-3:]
        raise SlamError(f"slam run failed on {seq_path.name}: {' | '.join(tail)}")
    stats: dict[str, Any] = json.loads((out_dir / "stats.json").read_text())
    stats["process_wall_s"] = wall
    return stats


def loop_off_config(run_dir: Path, dest: Path) -> Path | None:
    """A run's resolved config.yaml with ``loop_closure: false`` written to ``dest`` (None when
    that run had loop closure off already)."""
    import yaml

    from slam.core.atomic import write_atomic

    data = yaml.safe_load((run_dir / "config.yaml").read_text()) or {}
    if not data.get("loop_closure"):
        return None
    data["loop_closure"] = False
    dest.parent.mkdir(parents=True, exist_ok=True)
    write_atomic(dest, yaml.safe_dump(data, sort_keys=False))
    return dest


def ate_se3(seq_path: Path, trajectory: Path) -> float | None:
    """ATE RMSE (SE3 alignment) of one trajectory file or run folder against the sequence."""
    from slam.evaluation.evaluate import EvalOptions, ape_of, load_pair, prepare

    try:
        ref, est = load_pair(seq_path, trajectory, EvalOptions())
    except SlamError:
        return None
    return float(ape_of(prepare(ref, est, EvalOptions(align="se3"))).stats["rmse"])


def evaluate_run(seq_path: Path, run_dir: Path) -> dict[str, Any]:
    """Accuracy of a run against the sequence's ground truth (empty when it has none)."""
    from slam.evaluation.evaluate import (
        EvalOptions,
        ape_of,
        load_pair,
        prepare,
        resolve_lengths,
        rpe_of,
        segments_of,
    )

    try:
        ref, est = load_pair(seq_path, run_dir, EvalOptions())
    except SlamError as exc:
        return {"eval_error": str(exc)}
    out: dict[str, Any] = {}
    p_se3 = prepare(ref, est, EvalOptions(align="se3"))
    p_yaw = prepare(ref, est, EvalOptions(align="posyaw"))
    out["ate_se3_m"] = ape_of(p_se3).stats["rmse"]
    out["ate_posyaw_m"] = ape_of(p_yaw).stats["rmse"]
    path_m = ref.trajectory.path_length_m() if hasattr(ref, "trajectory") else None
    out["gt_path_m"] = path_m
    for delta in (1.0, 10.0):
        try:
            out[f"rpe_{delta:g}m_m"] = rpe_of(p_se3, "trans", delta, "metres").stats["rmse"]
        except Exception:  # path shorter than the delta
            out[f"rpe_{delta:g}m_m"] = None
    closed = run_dir / "trajectory_loop_closed.tum"
    if closed.exists():
        out["ate_loop_closed_m"] = ate_se3(seq_path, closed)
    odometry = run_dir / "trajectory_odometry.tum"
    if odometry.exists():
        out["ate_odometry_m"] = ate_se3(seq_path, odometry)
    try:
        segs = segments_of(p_yaw, resolve_lengths("rpg", p_yaw.ref_poses))
        out["drift_pct"] = float(sum(s.stats["mean"] for s in segs) / len(segs))
    except Exception:
        out["drift_pct"] = None
    return out


def false_loops(seq_path: Path, stats: dict[str, Any]) -> int | None:
    """Accepted loops whose two keyframes were not at the same place by the ground truth.

    Same place: body positions within 2 m and camera viewing directions within 45 degrees (a
    verified loop needs shared structure in view). None without ground truth or loops.
    """
    loops = (stats.get("loop_closure") or {}).get("loops")
    if not loops:
        return 0 if loops is not None else None
    from datasets.open import open_sequence
    from slam.core.geometry import quat_wxyz_to_matrix

    gt = open_sequence(seq_path).ground_truth
    if gt is None or len(gt) == 0:
        return None

    def pose_at(t_ns: int) -> tuple[np.ndarray, np.ndarray]:
        i = int(np.clip(np.searchsorted(gt.t_ns, t_ns), 0, len(gt) - 1))
        return gt.positions_m[i], quat_wxyz_to_matrix(gt.q_wxyz[i])

    false = 0
    for loop in loops:
        if loop.get("query_t_ns") is None or loop.get("match_t_ns") is None:
            continue
        pa, ra = pose_at(int(loop["query_t_ns"]))
        pb, rb = pose_at(int(loop["match_t_ns"]))
        # EuRoC-style body: the camera looks along body x/z; compare all axes' agreement
        angle_deg = float(np.degrees(rotation_angle_rad(ra.T @ rb)))
        if np.linalg.norm(pa - pb) > 2.0 or angle_deg > 45.0:
            false += 1
    return false


def summarise(name: str, stats: dict[str, Any], acc: dict[str, Any]) -> dict[str, Any]:
    be = stats.get("backend") or {}
    fe = stats.get("latency", {}).get("frontend_frame", {})
    frames_in = max(int(stats.get("frames_in", 0)), 1)
    return {
        "sequence": name,
        **acc,
        "completion_pct": 100.0 * stats.get("frames_tracked", 0) / frames_in,
        "tracking_losses": stats.get("tracking_losses"),
        "loops_accepted": (stats.get("loop_closure") or {}).get("accepted"),
        "init_s": be.get("initialised_after_s"),
        "real_time_factor": stats.get("real_time_factor"),
        "frontend_p50_ms": fe.get("p50_ms"),
        "frontend_p99_ms": fe.get("p99_ms"),
        # of the p99 frame time, how much a frame's CPU work and its run-queue wait take (p99s)
        "frontend_cpu_p99_ms": stats.get("latency", {}).get("frontend_frame_cpu", {}).get("p99_ms"),
        "frontend_runqueue_p99_ms": (
            stats.get("latency", {}).get("frontend_frame_runqueue", {}).get("p99_ms")
        ),
        "backend_p50_ms": (be.get("update") or {}).get("p50_ms"),
        "backend_p99_ms": (be.get("update") or {}).get("p99_ms"),
        "backend_resets": be.get("resets"),
        "peak_rss_mb": stats.get("peak_rss_mb"),
        "end_of_run_s": stats.get("end_of_run_s"),
        "keyframes": stats.get("keyframes"),
        "old_landmarks_on_revisits": (stats.get("map_reuse") or {}).get(
            "old_landmark_fraction_on_revisits"
        ),
    }


COLUMNS = (
    ("sequence", "sequence", "{}"),
    ("ate_se3_m", "ATE se3 (m)", "{:.4f}"),
    ("ate_posyaw_m", "ATE posyaw (m)", "{:.4f}"),
    ("ate_odometry_m", "ATE odometry (m)", "{:.4f}"),
    ("ate_loop_closed_m", "ATE loop-closed (m)", "{:.4f}"),
    ("ate_loop_off_m", "ATE loop off (m)", "{:.4f}"),
    ("loop_ratio", "closed/off", "{:.2f}"),
    ("rpe_1m_m", "RPE 1 m (m)", "{:.4f}"),
    ("rpe_10m_m", "RPE 10 m (m)", "{:.4f}"),
    ("drift_pct", "drift (%)", "{:.3f}"),
    ("completion_pct", "completion (%)", "{:.1f}"),
    ("loops_accepted", "loops", "{}"),
    ("false_loops", "false loops", "{}"),
    ("old_landmarks_on_revisits", "old landmarks on revisits", "{:.2f}"),
    ("init_s", "init (s)", "{:.2f}"),
    ("real_time_factor", "RTF", "{:.2f}"),
    ("end_of_run_s", "end (s)", "{:.1f}"),
    ("frontend_p50_ms", "FE p50 (ms)", "{:.1f}"),
    ("frontend_p99_ms", "FE p99 (ms)", "{:.1f}"),
    ("backend_p50_ms", "BE p50 (ms)", "{:.1f}"),
    ("backend_p99_ms", "BE p99 (ms)", "{:.1f}"),
    ("peak_rss_mb", "peak memory (MB)", "{:.0f}"),
)


def _fmt(value: Any, fmt: str) -> str:
    if value is None:
        return "-"
    try:
        return fmt.format(value)
    except (ValueError, TypeError):
        return str(value)


def markdown_table(rows: list[dict[str, Any]], old: dict[str, dict[str, Any]] | None = None) -> str:
    """One row per run; with ``old`` (by sequence), each number also shows its change."""
    head = "| " + " | ".join(title for _, title, _ in COLUMNS) + " |"
    sep = "|" + "|".join("---" for _ in COLUMNS) + "|"
    lines = [head, sep]
    for row in rows:
        cells = []
        prev = (old or {}).get(row["sequence"])
        for key, _, fmt in COLUMNS:
            cell = _fmt(row.get(key), fmt)
            if prev is not None and key != "sequence":
                a, b = row.get(key), prev.get(key)
                if isinstance(a, (int, float)) and isinstance(b, (int, float)):
                    cell += f" ({'+' if a - b >= 0 else ''}{_fmt(a - b, fmt)})"
            cells.append(cell)
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def run_benchmark(
    out_dir: Path,
    sequences: list[Path],
    suite: tuple[SuiteEntry, ...] | None,
    cache_dir: Path,
    preset: str | None = None,
    extra_args: list[str] | None = None,
    compare: Path | None = None,
    loop_baseline: bool = True,
) -> tuple[list[dict[str, Any]], str]:
    """Run everything, write ``results.json`` and ``results.md`` to ``out_dir``."""
    from slam.core.atomic import write_atomic

    out_dir.mkdir(parents=True, exist_ok=True)
    todo: list[tuple[str, Path, bool]] = []
    for entry in suite or ():
        todo.append((entry.name, ensure_sequence(entry, cache_dir), entry.revisits))
    for path in sequences:
        if not path.exists():
            raise SlamError(f"{path}: no such sequence")
        todo.append((path.stem if path.is_file() else path.name, path, False))
    rows = []
    for name, path, revisits in todo:
        run_dir = out_dir / "runs" / name
        print(f"running {name} ...", flush=True)
        stats = run_one(path, run_dir, preset, extra_args or [])
        acc = evaluate_run(path, run_dir)
        acc["false_loops"] = false_loops(path, stats)
        if loop_baseline and revisits:
            off_cfg = loop_off_config(run_dir, out_dir / "runs" / f"{name}-loop-off.yaml")
            if off_cfg is not None:
                print(f"running {name} with loop closure off ...", flush=True)
                off_dir = out_dir / "runs" / f"{name}-loop-off"
                off_args = [a for a in (extra_args or [])]
                run_one(path, off_dir, str(off_cfg), off_args)
                acc["ate_loop_off_m"] = ate_se3(path, off_dir)
                closed_m, off_m = acc.get("ate_loop_closed_m"), acc["ate_loop_off_m"]
                if closed_m is not None and off_m:
                    acc["loop_ratio"] = closed_m / off_m
        row = summarise(name, stats, acc)
        write_atomic(run_dir / "bench.json", json.dumps(row, indent=2) + "\n")
        rows.append(row)
        print(
            f"  ATE se3 {_fmt(row.get('ate_se3_m'), '{:.4f}')} m, "
            f"RTF {_fmt(row['real_time_factor'], '{:.2f}')}, "
            f"FE p99 {_fmt(row['frontend_p99_ms'], '{:.1f}')} ms"
            + (
                f", loop-closed / off {_fmt(row.get('ate_loop_closed_m'), '{:.4f}')} / "
                f"{_fmt(row.get('ate_loop_off_m'), '{:.4f}')} m"
                if row.get("ate_loop_off_m") is not None
                else ""
            ),
            flush=True,
        )
    old = None
    if compare is not None:
        try:
            old_rows = json.loads(Path(compare).read_text())["runs"]
        except (OSError, ValueError, KeyError) as exc:
            raise SlamError(
                f"--compare {compare}: not a results.json from slam bench ({exc})"
            ) from None
        old = {r["sequence"]: r for r in old_rows}
    table = markdown_table(rows, old)
    meta = {
        "suite_version": SUITE_VERSION,
        "suite": [asdict(e) for e in (suite or ())],
        "preset": preset,
        "extra_args": extra_args or [],
        "loop_baseline": loop_baseline,
        "date": time.strftime("%Y-%m-%d %H:%M:%S"),
        "runs": rows,
    }
    write_atomic(out_dir / "results.json", json.dumps(meta, indent=2) + "\n")
    write_atomic(out_dir / "results.md", table)
    return rows, table

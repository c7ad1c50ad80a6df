"""The project's benchmark: a batch (``tools/batch``) over the built-in suite, and its table.

The standard suite is synthetic (exact ground truth, EuRoC-grade simulated IMU noise), generated
once per definition and cached as MCAP files (deterministic: same definition, same bytes). Each
run is a separate `slam run` process at ``--speed max`` without a viewer, so peak memory and
timing belong to that run alone, one at a time on the local engine by default. Per run (see
``tools/batch/measure.py``): ATE RMSE (se3 and posyaw), RPE at 1 m and 10 m, drift, completion,
initialisation time, real-time factor, front-end latency p50/p99, back-end update p50/p99, peak
RSS. With repeats, the table shows each number's median over them.

Loop closure: on suite sequences flagged ``revisits`` (they come back to places seen long
before, after drift has accumulated), a second configuration of the same sequence, the same
configuration with ``loop_closure: false``, gives "the same run's ATE with loop closure off" and
the ratio loop-closed / off. A separate run, not the online trajectory of the loop-closure run:
that one is also changed by relocalisation against the map. ``--no-loop-baseline`` skips it.
"""

from __future__ import annotations

import dataclasses
import json
import os
import statistics
import subprocess
import sys
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

from slam.core.errors import SlamError
from tools.batch.measure import COLUMNS, fmt
from tools.batch.spec import BatchSpec, ConfigChoice, SequenceChoice

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
    camera: str = "clean"  # "clean" or "realistic": `slam synth --camera`

    def file_name(self) -> str:
        camera = "" if self.camera == "clean" else f"-{self.camera}"
        return (
            f"{self.name}-{self.profile}-{self.duration_s:g}s-seed{self.seed}{camera}"
            f"-v{SUITE_VERSION}.mcap"
        )


STANDARD_SUITE = (
    SuiteEntry("room-figure8", "figure8", 60.0, 1, "room"),
    SuiteEntry("room-loop", "loop", 80.0, 2, "room"),
    SuiteEntry("room-aggressive", "aggressive", 60.0, 3, "room"),
    SuiteEntry("hall", "hall", 140.0, 4, "hall"),
)


RENDER_SEED_STEP = 10  # --renders K: seeds s, s + 10, s + 20, ... of each suite entry


def suite_variant(
    suite: tuple[SuiteEntry, ...],
    duration_s: float | None = None,
    camera: str = "clean",
    renders: int = 1,
) -> tuple[SuiteEntry, ...]:
    """``suite`` cut to ``duration_s`` per sequence (smoke tests, quick checks), rendered with
    ``camera`` effects, and ``renders`` renders of each entry that differ only in their noise
    seed (IMU noise, camera effects: ``slam synth --seed``), so that medians are over
    renders and not over one draw. The trajectory and the scene are the same in every render."""
    return tuple(
        dataclasses.replace(
            e,
            duration_s=e.duration_s if duration_s is None else min(e.duration_s, duration_s),
            seed=e.seed + RENDER_SEED_STEP * k,
            camera=camera,
        )
        for e in suite
        for k in range(renders)
    )


def quick_suite(duration_s: float) -> tuple[SuiteEntry, ...]:
    """The standard suite cut to ``duration_s`` per sequence (smoke tests, quick checks)."""
    return suite_variant(STANDARD_SUITE, duration_s)


def default_cache_dir() -> Path:
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(base) / "pyvislam" / "bench"


def ensure_sequence(entry: SuiteEntry, cache_dir: Path, progress: bool = True) -> Path:
    """The cached MCAP of a suite entry, generated first if missing."""
    from datasets.mcap_io import write_sequence_mcap
    from datasets.synth import make_synthetic_sequence
    from datasets.synth.camera_model import rig_effects

    path = cache_dir / entry.file_name()
    if path.exists():
        return path
    cache_dir.mkdir(parents=True, exist_ok=True)
    print(f"generating {path.name} (cached for later runs)", flush=True)
    camera, imu_effects = rig_effects(entry.camera)
    seq = make_synthetic_sequence(
        profile=entry.profile,
        duration_s=entry.duration_s,
        seed=entry.seed,
        camera=camera,
        imu_effects=imu_effects,
    )
    write_sequence_mcap(seq, path, progress=progress)
    return path


def run_one(
    seq_path: Path,
    out_dir: Path,
    preset: str | None,
    extra_args: list[str],
    speed: str = "max",
    tree: Path | None = None,
) -> dict[str, Any]:
    """`slam run` in its own process; returns its stats.json (raises on failure).

    ``tree``: run that source tree's code (a checkout or an exported commit, with this
    interpreter's packages) instead of the installed one: ``tools.bench_ab``."""
    cmd = [
        sys.executable,
        "-m",
        "tools.cli",
        "run",
        str(seq_path.resolve()),
        "--out",
        str(out_dir.resolve()),
        "--speed",
        speed,
        "--no-progress",
        *extra_args,
    ]
    if preset:
        cmd += ["--config", str(Path(preset).resolve()) if Path(preset).is_file() else preset]
    env = None
    if tree is not None:
        env = {**os.environ, "PYTHONPATH": str(tree.resolve())}
    t0 = time.perf_counter()
    proc = subprocess.run(
        cmd, capture_output=True, text=True, cwd=None if tree is None else tree, env=env
    )
    wall = time.perf_counter() - t0
    if proc.returncode != 0:
        tail = (proc.stderr or proc.stdout).strip().splitlines()[-3:]
        raise SlamError(f"slam run failed on {seq_path.name}: {' | '.join(tail)}")
    stats: dict[str, Any] = json.loads((out_dir / "stats.json").read_text())
    stats["process_wall_s"] = wall
    return stats


LOOP_OFF = "loop-off"


def loop_off_choice(base: ConfigChoice, default_preset: str) -> ConfigChoice | None:
    """``base`` with loop closure off, for the baseline runs; None when ``base`` has loop
    closure off already (``default_preset``: what slam run picks when ``base`` names none)."""
    from slam.config import load_config

    if not base.overrides.get("loop_closure", load_config(base.base, default_preset).loop_closure):
        return None
    return ConfigChoice(LOOP_OFF, base.base, {**base.overrides, "loop_closure": False})


def markdown_table(rows: list[dict[str, Any]], old: dict[str, dict[str, Any]] | None = None) -> str:
    """One row per sequence; with ``old`` (by sequence), each number also shows its change
    (and each ATE its ratio to the old one: realistic over clean, new code over old)."""
    head = "| " + " | ".join(title for _, title, _ in COLUMNS) + " |"
    sep = "|" + "|".join("---" for _ in COLUMNS) + "|"
    lines = [head, sep]
    for row in rows:
        cells = []
        prev = (old or {}).get(row["sequence"])
        for key, _, spec in COLUMNS:
            cell = fmt(row.get(key), spec)
            if prev is not None and key != "sequence":
                a, b = row.get(key), prev.get(key)
                if isinstance(a, (int, float)) and isinstance(b, (int, float)):
                    ratio = f", x{a / b:.2f}" if key.startswith("ate_") and b > 0 else ""
                    cell += f" ({'+' if a - b >= 0 else ''}{fmt(a - b, spec)}{ratio})"
            cells.append(cell)
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def suite_run_name(entry: SuiteEntry, suite: tuple[SuiteEntry, ...]) -> str:
    """A suite entry's name in the batch: its suite name, with its seed when the suite holds
    several renders of it (``--renders``); the table's rows are the suite names."""
    renders = sum(e.name == entry.name for e in suite)
    return entry.name if renders == 1 else f"{entry.name}-seed{entry.seed}"


def bench_spec(
    sequences: list[Path],
    suite: tuple[SuiteEntry, ...] | None,
    cache_dir: Path,
    preset: str | None = None,
    extra_args: list[str] | None = None,
    loop_baseline: bool = True,
    repeats: int = 1,
    sequential: bool = False,
    progress: bool = True,
) -> BatchSpec:
    """The batch of a benchmark: every sequence with ``preset``, and the suite's revisiting
    sequences also with loop closure off."""
    base = ConfigChoice(preset or "default", preset)
    loop_off = loop_off_choice(base, "euroc-stereo-imu") if loop_baseline else None
    seqs = []
    for entry in suite or ():
        path = ensure_sequence(entry, cache_dir, progress)
        both = entry.revisits and loop_off is not None
        seqs.append(
            SequenceChoice(
                path,
                suite_run_name(entry, suite or ()),
                (base.name, LOOP_OFF) if both else (base.name,),
            )
        )
    for path in sequences:
        if not path.exists():
            raise SlamError(f"{path}: no such sequence")
        seqs.append(SequenceChoice(path, path.stem if path.is_file() else path.name, (base.name,)))
    return BatchSpec(
        seqs,
        [base] + ([loop_off] if loop_off is not None else []),
        repeats=repeats,
        speed="max",
        sequential=sequential,
        run_args=list(extra_args or []),
    )


def median(values: list[Any]) -> Any:
    """The median of the numbers among ``values`` (None and other non-numbers left out), an
    int when they all are; None without any."""
    numbers = [v for v in values if isinstance(v, (int, float)) and not isinstance(v, bool)]
    if not numbers:
        return None
    m = statistics.median(numbers)
    return int(m) if all(isinstance(v, int) for v in numbers) and m == int(m) else m


def bench_rows(
    records: list[dict[str, Any]], base_config: str, rows_of: dict[str, str] | None = None
) -> list[dict[str, Any]]:
    """One row per sequence: the median of every number over the repeats of the base
    configuration, with the loop-off runs' ATE and the ratio loop-closed / off.

    ``rows_of``: a batch sequence's row when it is not its own (the renders of one suite
    entry share its row: medians over renders and repeats together)."""
    rows_of = rows_of or {}
    by_seq: dict[str, dict[str, list[dict[str, Any]]]] = {}
    for r in records:
        if r.get("status") == "ok":
            seq = rows_of.get(r["sequence"], r["sequence"])
            by_seq.setdefault(seq, {}).setdefault(r["config"], []).append(r["metrics"])
    rows = []
    for seq in dict.fromkeys(rows_of.get(r["sequence"], r["sequence"]) for r in records):
        runs = by_seq.get(seq, {})
        base = runs.get(base_config, [])
        keys = dict.fromkeys(k for m in base for k in m)
        row: dict[str, Any] = {"sequence": seq, "repeats": len(base)}
        for key in keys:
            if key != "sequence":
                row[key] = median([m.get(key) for m in base])
        if base and "eval_error" in keys:
            row["eval_error"] = base[0].get("eval_error")
        off = runs.get(LOOP_OFF)
        if off:
            row["ate_loop_off_m"] = median([m.get("ate_se3_m") for m in off])
            closed, off_m = row.get("ate_loop_closed_m"), row["ate_loop_off_m"]
            if closed is not None and off_m:
                row["loop_ratio"] = closed / off_m
        rows.append(row)
    return rows


def run_benchmark(
    out_dir: Path,
    sequences: list[Path],
    suite: tuple[SuiteEntry, ...] | None,
    cache_dir: Path,
    preset: str | None = None,
    extra_args: list[str] | None = None,
    compare: Path | None = None,
    loop_baseline: bool = True,
    repeats: int = 1,
    sequential: bool = False,
    engine: str = "local",
    address: str = "auto",
    progress: bool = True,
) -> tuple[list[dict[str, Any]], str, int]:
    """Run the benchmark's batch in ``out_dir`` (resumable), write ``results.json`` and
    ``results.md`` (the table) beside the batch's report; returns the rows, the table and how
    many runs failed."""
    from slam.core.atomic import write_atomic
    from tools.batch.runner import run_batch

    old = None
    if compare is not None:  # checked before hours of runs, not after
        try:
            old_rows = json.loads(Path(compare).read_text())["runs"]
            old = {r["sequence"]: r for r in old_rows}
        except (OSError, ValueError, KeyError, TypeError) as exc:
            raise SlamError(
                f"--compare {compare}: not a results.json from slam bench ({exc})"
            ) from None
    spec = bench_spec(
        sequences,
        suite,
        cache_dir,
        preset,
        extra_args,
        loop_baseline,
        repeats,
        sequential,
        progress,
    )

    def line(record: dict[str, Any]) -> None:
        m = record.get("metrics") or {}
        what = f"{record['run_id']}: "
        if record["status"] != "ok":
            print(what + f"FAILED: {record.get('error')}", flush=True)
            return
        print(
            what + f"ATE se3 {fmt(m.get('ate_se3_m'), '{:.4f}')} m, "
            f"RTF {fmt(m.get('real_time_factor'), '{:.2f}')}, "
            f"FE p99 {fmt(m.get('frontend_p99_ms'), '{:.1f}')} ms",
            flush=True,
        )

    result = run_batch(
        spec,
        out_dir,
        engine=engine,
        address=address,
        progress=progress,
        title="slam bench",
        on_record=line,
    )
    from tools.batch.report import read_record

    records = [r for t in result.tasks if (r := read_record(out_dir, t)) is not None]
    rows_of = {suite_run_name(e, suite or ()): e.name for e in suite or ()}
    rows = bench_rows(records, spec.configs[0].name, rows_of)
    table = markdown_table(rows, old)
    meta = {
        "suite_version": SUITE_VERSION,
        "suite": [asdict(e) for e in (suite or ())],
        "preset": preset,
        "extra_args": extra_args or [],
        "loop_baseline": loop_baseline,
        "repeats": repeats,
        "sequential": sequential,
        "failed_runs": [f"{r['run_id']}: {r.get('error')}" for r in records if r["status"] != "ok"],
        "date": time.strftime("%Y-%m-%d %H:%M:%S"),
        "runs": rows,
    }
    write_atomic(out_dir / "results.json", json.dumps(meta, indent=2) + "\n")
    write_atomic(out_dir / "results.md", table)
    return rows, table, result.failed

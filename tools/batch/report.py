"""A batch's folder: run folders (resumption), the gathered results and the report tables.

``OUT/runs/<sequence>/<configuration>/rep<N>/`` holds a run's `slam run` outputs, its log
(``slam_run.log``), its evaluation (``eval/``) and, written last and atomically, ``run.json``:
status (``ok`` or ``failed`` with a one-line error), the run's numbers and the fingerprint of
what made them. A run whose ``run.json`` says ``ok`` with the same fingerprint is finished: a
restarted batch skips it. Failed runs are run again.

The report, rewritten (atomically) after every run: ``report.md`` and ``report.csv`` (per
sequence x configuration: median and spread over the repeats, completion, real-time factor,
latencies), ``runs.csv`` (every run), ``runs.json`` (the spec, every run's record, the groups).
"""

from __future__ import annotations

import csv
import io
import json
import shutil
import statistics
import time
from pathlib import Path
from typing import Any

from slam.core.atomic import write_atomic
from slam.core.messages import BatchOutcome, BatchTask
from tools.batch.measure import COLUMNS, fmt

RUN_RECORD = "run.json"
#: The report's numbers per sequence x configuration, in column order (titles from COLUMNS).
REPORT_METRICS = (
    "ate_se3_m",
    "ate_posyaw_m",
    "rpe_1m_m",
    "ate_loop_closed_m",
    "drift_pct",
    "completion_pct",
    "real_time_factor",
    "frontend_p50_ms",
    "frontend_p99_ms",
    "backend_p99_ms",
    "end_of_run_s",
    "peak_rss_mb",
    "process_wall_s",
)
_TITLES = {key: (title, spec) for key, title, spec in COLUMNS} | {
    "process_wall_s": ("run wall (s)", "{:.1f}")
}


def run_dir(out_dir: Path, task: BatchTask) -> Path:
    return out_dir / "runs" / task.run_id


def read_record(out_dir: Path, task: BatchTask) -> dict[str, Any] | None:
    """The run's ``run.json`` (None when absent or unreadable: a run cut short)."""
    try:
        record = json.loads((run_dir(out_dir, task) / RUN_RECORD).read_text())
    except (OSError, ValueError):
        return None
    return record if isinstance(record, dict) else None


def is_finished(out_dir: Path, task: BatchTask) -> bool:
    record = read_record(out_dir, task)
    return (
        record is not None
        and record.get("status") == "ok"
        and record.get("fingerprint") == task.fingerprint
    )


def store(out_dir: Path, task: BatchTask, outcome: BatchOutcome) -> dict[str, Any]:
    """Write a run's files into its folder (replacing what a cut-short attempt left), then its
    record; returns the record."""
    folder = run_dir(out_dir, task)
    if folder.exists():
        shutil.rmtree(folder)
    for rel, data in outcome.files.items():
        write_atomic(folder / rel, data)
    record = {
        "run_id": task.run_id,
        "sequence": task.sequence,
        "config": task.config,
        "repeat": task.repeat,
        "status": "ok" if outcome.ok else "failed",
        "error": outcome.error,
        "host": outcome.host,
        "process_wall_s": outcome.process_wall_s,
        "sequence_path": task.sequence_path,
        "run_args": list(task.run_args),
        "fingerprint": task.fingerprint,
        "finished": time.strftime("%Y-%m-%d %H:%M:%S"),
        "metrics": outcome.metrics,
    }
    write_atomic(folder / RUN_RECORD, json.dumps(record, indent=1) + "\n")
    return record


def value_of(record: dict[str, Any], key: str) -> Any:
    if key == "process_wall_s":
        return record.get("process_wall_s")
    return (record.get("metrics") or {}).get(key)


def groups(tasks: list[BatchTask], records: dict[str, dict[str, Any]]) -> list[dict[str, Any]]:
    """Per sequence x configuration (in task order): runs, ok runs, and for every report metric
    its median, min and max over the ok runs (None without values)."""
    order: dict[tuple[str, str], list[BatchTask]] = {}
    for task in tasks:
        order.setdefault((task.sequence, task.config), []).append(task)
    out = []
    for (sequence, config), members in order.items():
        done = [records[t.run_id] for t in members if t.run_id in records]
        ok = [r for r in done if r.get("status") == "ok"]
        row: dict[str, Any] = {
            "sequence": sequence,
            "config": config,
            "runs": len(members),
            "runs_finished": len(done),
            "runs_ok": len(ok),
        }
        for key in REPORT_METRICS:
            values = [float(v) for r in ok if isinstance(v := value_of(r, key), (int, float))]
            row[key] = {
                "median": statistics.median(values) if values else None,
                "min": min(values) if values else None,
                "max": max(values) if values else None,
                "n": len(values),
            }
        out.append(row)
    return out


def _cell(stat: dict[str, Any], spec: str) -> str:
    if stat["median"] is None:
        return "-"
    if stat["n"] == 1:
        return fmt(stat["median"], spec)
    return f"{fmt(stat['median'], spec)} ({fmt(stat['min'], spec)}-{fmt(stat['max'], spec)})"


def markdown(
    rows: list[dict[str, Any]],
    failures: list[dict[str, Any]],
    unevaluated: list[dict[str, Any]],
    title: str,
) -> str:
    """The report: one row per sequence x configuration, median (min-max) over the repeats."""
    head = ["sequence", "configuration", "runs ok"] + [_TITLES[k][0] for k in REPORT_METRICS]
    lines = [
        f"# {title}",
        "",
        "Per sequence x configuration: the median over the repeats that finished, (min-max) when "
        "there are several. ATE: RMSE of the absolute trajectory error after se3 or posyaw "
        "alignment; RPE over 1 m of path; RTF: real-time factor of the tracking; FE/BE: "
        "front-end frame and back-end update latency percentiles; run wall: the `slam run` "
        "process.",
        "",
        "| " + " | ".join(head) + " |",
        "|" + "|".join(["---"] * 2 + ["---:"] * (len(head) - 2)) + "|",
    ]
    for row in rows:
        cells = [row["sequence"], row["config"], f"{row['runs_ok']}/{row['runs']}"]
        cells += [_cell(row[k], _TITLES[k][1]) for k in REPORT_METRICS]
        lines.append("| " + " | ".join(cells) + " |")
    if failures:
        lines += ["", "Failed runs:", ""]
        lines += [f"- `{r['run_id']}`: {r.get('error') or 'failed'}" for r in failures]
    if unevaluated:
        lines += ["", "Runs without an evaluation (no accuracy columns):", ""]
        lines += [f"- `{r['run_id']}`: {r['metrics']['eval_error']}" for r in unevaluated]
    return "\n".join(lines) + "\n"


def summary_csv(rows: list[dict[str, Any]]) -> str:
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(
        ["sequence", "configuration", "runs", "runs_ok"]
        + [f"{k}_{s}" for k in REPORT_METRICS for s in ("median", "min", "max")]
    )
    for row in rows:
        w.writerow(
            [row["sequence"], row["config"], row["runs"], row["runs_ok"]]
            + [_csv(row[k][s]) for k in REPORT_METRICS for s in ("median", "min", "max")]
        )
    return buf.getvalue()


def runs_csv(records: list[dict[str, Any]]) -> str:
    keys = [k for k, _, _ in COLUMNS if k != "sequence"]
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(
        ["run_id", "sequence", "configuration", "repeat", "status", "error", "host"]
        + ["process_wall_s", *keys]
    )
    for r in records:
        m = r.get("metrics") or {}
        w.writerow(
            [
                r["run_id"],
                r["sequence"],
                r["config"],
                r["repeat"],
                r["status"],
                r.get("error") or "",
            ]
            + [r.get("host", ""), _csv(r.get("process_wall_s"))]
            + [_csv(m.get(k)) for k in keys]
        )
    return buf.getvalue()


def _csv(value: Any) -> str:
    if value is None:
        return ""
    return repr(value) if isinstance(value, float) else str(value)


def write_report(
    out_dir: Path, tasks: list[BatchTask], spec: dict[str, Any], title: str = "slam batch"
) -> list[dict[str, Any]]:
    """Gather every run's record and (re)write the tables; returns the per-group rows."""
    records = {t.run_id: r for t in tasks if (r := read_record(out_dir, t)) is not None}
    ordered = [records[t.run_id] for t in tasks if t.run_id in records]
    rows = groups(tasks, records)
    failures = [r for r in ordered if r.get("status") != "ok"]
    unevaluated = [r for r in ordered if (r.get("metrics") or {}).get("eval_error")]
    write_atomic(out_dir / "report.md", markdown(rows, failures, unevaluated, title))
    write_atomic(out_dir / "report.csv", summary_csv(rows))
    write_atomic(out_dir / "runs.csv", runs_csv(ordered))
    payload = {"spec": spec, "runs": ordered, "summary": rows}
    write_atomic(out_dir / "runs.json", json.dumps(payload, indent=1) + "\n")
    return rows

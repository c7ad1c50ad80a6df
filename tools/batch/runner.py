"""Run a batch: build its runs, skip the finished ones, execute the rest, write as they finish."""

from __future__ import annotations

import shutil
import signal
import sys
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from types import FrameType
from typing import Any

import yaml

from slam.core.atomic import write_atomic
from slam.core.errors import SlamError
from slam.core.messages import BatchTask
from tools.batch import plots, report
from tools.batch.engines import make_engine
from tools.batch.spec import BatchSpec, build_tasks

#: Plots are redrawn at most this often while runs finish (and always at the end), s.
PLOT_EVERY_S = 30.0


@dataclass
class BatchResult:
    tasks: list[BatchTask]
    skipped: int  # finished in an earlier attempt
    ran: int
    failed: int
    rows: list[dict[str, Any]]  # per sequence x configuration (report.groups)
    wall_s: float


def _raise_interrupt(signum: int, frame: FrameType | None) -> None:
    raise KeyboardInterrupt


def write_outputs(
    out_dir: Path, tasks: list[BatchTask], spec: dict[str, Any], title: str, plots_too: bool
) -> list[dict[str, Any]]:
    rows = report.write_report(out_dir, tasks, spec, title)
    if plots_too:
        records = {t.run_id: r for t in tasks if (r := report.read_record(out_dir, t)) is not None}
        plots.ate_boxplot(out_dir / "ate_boxplot.png", tasks, records)
        plots.trajectories_plot(out_dir / "trajectories.png", out_dir, tasks, records)
    return rows


def run_batch(
    spec: BatchSpec,
    out_dir: Path,
    engine: str = "local",
    address: str = "auto",
    jobs: int | None = None,
    progress: bool = True,
    title: str = "slam batch",
    on_record: Any = None,
) -> BatchResult:
    """Run every run of ``spec`` not yet finished in ``out_dir``; (re)write the report.

    ``on_record(record)`` is called in this thread after each run is stored (``slam bench``
    prints a line). Ctrl-C or SIGTERM stops the runs going (they are not recorded: a restart runs
    them) and leaves the report of what finished; the KeyboardInterrupt goes on to the caller.
    """
    from tqdm import tqdm

    t0 = time.perf_counter()
    if out_dir.exists() and not out_dir.is_dir():
        raise SlamError(f"--out {out_dir} exists and is not a folder")
    tasks = build_tasks(spec)  # checks every configuration before anything runs
    if not tasks:
        raise SlamError("the batch has no runs (no sequence, or no configuration for them)")
    out_dir.mkdir(parents=True, exist_ok=True)
    spec_data = spec.to_dict()
    write_atomic(out_dir / "batch.yaml", yaml.safe_dump(spec_data, sort_keys=False))
    scratch = out_dir / ".scratch"
    shutil.rmtree(scratch, ignore_errors=True)  # what a killed batch's runs left
    todo = [t for t in tasks if not report.is_finished(out_dir, t)]
    skipped = len(tasks) - len(todo)
    write_outputs(out_dir, tasks, spec_data, title, plots_too=True)
    runner = make_engine(engine, spec.cpus_per_run, scratch, address, jobs)
    by_id = {t.run_id: t for t in todo}
    ran = failed = 0
    in_main = threading.current_thread() is threading.main_thread()
    previous = signal.getsignal(signal.SIGTERM) if in_main else None
    if in_main:  # SIGTERM stops the batch as Ctrl-C does
        signal.signal(signal.SIGTERM, _raise_interrupt)
    bar = tqdm(
        total=len(tasks),
        initial=skipped,
        unit="run",
        desc=f"batch ({runner.name})",
        disable=not progress,
        file=sys.stderr,
        dynamic_ncols=True,
    )
    last_plot = time.perf_counter()
    try:
        for outcome in runner.run(todo):
            if outcome.stopped:
                continue
            task = by_id[outcome.run_id]
            record = report.store(out_dir, task, outcome)
            ran += 1
            failed += 0 if outcome.ok else 1
            now = time.perf_counter()
            plot_now = now - last_plot > PLOT_EVERY_S
            write_outputs(out_dir, tasks, spec_data, title, plots_too=plot_now)
            if plot_now:
                last_plot = now
            bar.update(1)
            bar.set_postfix(failed=failed, refresh=False)
            if not outcome.ok:
                bar.write(f"{task.run_id}: FAILED: {outcome.error}", file=sys.stderr)
            if on_record is not None:
                on_record(record)
    finally:
        bar.close()
        runner.close()
        if in_main:
            signal.signal(signal.SIGTERM, previous)
        rows = write_outputs(out_dir, tasks, spec_data, title, plots_too=True)
        shutil.rmtree(scratch, ignore_errors=True)
    return BatchResult(tasks, skipped, ran, failed, rows, time.perf_counter() - t0)

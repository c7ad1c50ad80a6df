"""One batch run on a worker: `slam run` in its own process, then its evaluation.

The same function runs on every engine (a local pool's thread, a Ray task on any node of a
cluster): it runs in a scratch folder, measures the run, and returns the folder's files in a
:class:`BatchOutcome`; the batch's driver writes them into the batch's folder. So a worker needs
the sequence (at ``task.sequence_path``) and pyvislam, not the batch's folder.
"""

from __future__ import annotations

import shutil
import socket
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

from slam.core.messages import BatchOutcome, BatchTask

#: How often a running `slam run` is checked for the batch being stopped, s.
POLL_S = 0.2
#: After SIGTERM, how long a stopped run gets to write its outputs before SIGKILL, s.
TERM_GRACE_S = 10.0


def slam_run_command(task: BatchTask, out_dir: Path, config_file: Path | None) -> list[str]:
    """The `slam run` command line of a task."""
    cmd = [sys.executable, "-m", "tools.cli", "run", task.sequence_path, "--out", str(out_dir)]
    cmd += ["--no-progress", *task.run_args]
    if config_file is not None:
        cmd += ["--config", str(config_file)]
    elif task.config_arg is not None:
        cmd += ["--config", task.config_arg]
    return cmd


def error_line(output: str, returncode: int) -> str:
    """One line saying why `slam run` failed: its own error line, else its last line."""
    lines = [ln.strip() for ln in output.strip().splitlines() if ln.strip()]
    errors = [ln for ln in lines if "error:" in ln]
    tail = errors[-1] if errors else (lines[-1] if lines else "no output")
    return f"slam run exited with {returncode}: {tail}"[:500]


def execute(
    task: BatchTask, stop: threading.Event | None = None, scratch_dir: str | None = None
) -> BatchOutcome:
    """Run ``task`` and measure it; never raises for a failed run (the outcome says why).

    ``stop`` (local engine): when set, the run is ended (SIGTERM, then SIGKILL) and the outcome
    is marked ``stopped``, i.e. not a result. ``scratch_dir``: where the run's temporary folder
    goes (default: the system's temporary folder).
    """
    from tools.batch.measure import measure_run

    scratch = Path(tempfile.mkdtemp(prefix="slam-batch-", dir=scratch_dir))
    out_dir = scratch / "run"
    config_file = None
    if task.config_yaml is not None:
        config_file = scratch / "config-in.yaml"
        config_file.write_text(task.config_yaml)
    log_path = scratch / "slam_run.log"
    t0 = time.perf_counter()
    ok, stopped, error = True, False, None
    try:
        with open(log_path, "w") as log:
            proc = subprocess.Popen(
                slam_run_command(task, out_dir, config_file),
                stdout=log,
                stderr=subprocess.STDOUT,
                stdin=subprocess.DEVNULL,
            )
            deadline = None if task.timeout_s is None else t0 + task.timeout_s
            while True:
                try:
                    proc.wait(timeout=POLL_S)
                    break
                except subprocess.TimeoutExpired:
                    pass
                late = deadline is not None and time.perf_counter() > deadline
                if late or (stop is not None and stop.is_set()):
                    proc.terminate()
                    try:
                        proc.wait(timeout=TERM_GRACE_S)
                    except subprocess.TimeoutExpired:
                        proc.kill()
                        proc.wait()
                    stopped = not late
                    ok, error = False, f"stopped after the timeout of {task.timeout_s} s"
                    break
        wall_s = time.perf_counter() - t0
        if ok and proc.returncode != 0:
            ok, error = False, error_line(log_path.read_text(errors="replace"), proc.returncode)
        metrics = {}
        if ok:
            try:
                metrics = measure_run(Path(task.sequence_path), out_dir, task.sequence)
            except Exception as exc:  # a run whose outputs cannot be measured is a failed run
                ok, error = False, f"evaluation failed: {type(exc).__name__}: {exc}"[:500]
        files = {"slam_run.log": log_path.read_bytes()}
        if out_dir.is_dir():
            for path in sorted(out_dir.rglob("*")):
                if path.is_file() and not path.name.startswith("."):
                    files[str(path.relative_to(out_dir))] = path.read_bytes()
        return BatchOutcome(
            task.run_id,
            ok,
            None if ok else (error or "failed").replace("\n", " "),
            files,
            metrics,
            wall_s,
            socket.gethostname(),
            stopped,
        )
    finally:
        shutil.rmtree(scratch, ignore_errors=True)

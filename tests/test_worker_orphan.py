"""A worker whose main process is killed ends by itself instead of waiting forever."""

from __future__ import annotations

import subprocess
import sys
import time
from pathlib import Path

SCRIPT = """
import os, signal
from slam.runtime.worker import WorkerCore, WorkerProcess

class Idle(WorkerCore):
    def handle(self, msg):
        return []

if __name__ == "__main__":
    worker = WorkerProcess("orphan-test", Idle, (), lambda item: False, lambda code: None, "loop")
    print(worker.proc.pid, flush=True)
    os.kill(os.getpid(), signal.SIGKILL)
"""


def _running(pid: int) -> bool:
    try:
        state = Path(f"/proc/{pid}/status").read_text()
    except FileNotFoundError:
        return False
    return "State:\tZ" not in state  # a zombie has exited (nobody reaped it yet)


def _worker_left_running(tmp_path: Path, main_script: str) -> int | None:
    """Run ``main_script`` (it prints its worker's pid, then SIGKILLs itself); the worker's
    pid if it is still running 10 s later, else None."""
    script = tmp_path / "main.py"
    script.write_text(main_script)
    proc = subprocess.run([sys.executable, str(script)], capture_output=True, text=True, timeout=60)
    assert proc.returncode == -9
    pid = int(proc.stdout.split()[0])
    deadline = time.monotonic() + 10.0
    while _running(pid) and time.monotonic() < deadline:
        time.sleep(0.1)
    return pid if _running(pid) else None


def test_worker_ends_when_the_main_process_is_killed(tmp_path: Path) -> None:
    pid = _worker_left_running(tmp_path, SCRIPT)
    assert pid is None, f"worker {pid} outlived its killed main process"


STOPPED = """
import os, signal
from slam.runtime.worker import WorkerCore, WorkerProcess

class Idle(WorkerCore):
    def handle(self, msg):
        return []

if __name__ == "__main__":
    worker = WorkerProcess(
        "stopped-test", Idle, (), lambda item: False, lambda code: None, "mapper", pausable=True
    )
    worker.wait_ready()
    assert worker.pause()
    print(worker.pid, flush=True)
    os.kill(os.getpid(), signal.SIGKILL)
"""


def test_stopped_worker_ends_when_the_main_process_is_killed(tmp_path: Path) -> None:
    """A pausable worker (the mapper, stopped while the front end tracks a frame) cannot poll
    for its parent while stopped: the kernel kills it with its parent (PR_SET_PDEATHSIG)."""
    pid = _worker_left_running(tmp_path, STOPPED)
    assert pid is None, f"stopped worker {pid} outlived its killed main process"

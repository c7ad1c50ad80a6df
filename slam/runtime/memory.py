"""Memory of the whole process tree: the main process and every worker it started.

``ru_maxrss`` gives one process's peak only (and ``RUSAGE_CHILDREN`` only children that have
ended and been waited for), so a sampler thread reads the tree's resident sizes every
``period_s`` from ``/proc`` (``_tree_pids``; psutil where that is missing): each process's own
peak comes from the kernel (``VmHWM``, exact), the total at its peak from the samples (the
tree's sum can peak between two samples). Resident sizes count pages shared between processes
(the reader's image ring, a worker just forked) in each of them.
"""

from __future__ import annotations

import os
import threading
from typing import Any

import psutil


def _status(pid: int) -> tuple[str, float, float] | None:
    """(name, resident MB, the kernel's peak resident MB ``VmHWM``) of process ``pid`` from
    ``/proc/PID/status``; None when it has ended (or this is not Linux)."""
    try:
        with open(f"/proc/{pid}/status") as f:
            fields = dict(line.split(":", 1) for line in f if ":" in line)
        rss = int(fields["VmRSS"].split()[0]) / 1024.0  # kB
        return fields["Name"].strip(), rss, int(fields["VmHWM"].split()[0]) / 1024.0
    except (OSError, KeyError, ValueError, IndexError):
        return None


def _tree_pids(root: int) -> list[int] | None:
    """``root`` and its descendants from ``/proc/PID/task/TID/children``: a few files of the
    tree's own. psutil's ``children()`` reads the status of every process on the machine, in
    Python: ~2-5 ms per sample on a shared machine, holding the GIL that the front end's thread
    needs back after each of its OpenCV calls. None without those files (a kernel without
    ``CONFIG_PROC_CHILDREN``, not Linux)."""
    if not os.path.exists(f"/proc/{root}/task/{root}/children"):
        return None
    pids, todo = [], [root]
    while todo:
        pid = todo.pop()
        pids.append(pid)
        try:
            tasks = os.listdir(f"/proc/{pid}/task")
        except OSError:
            continue  # ended
        for task in tasks:
            try:
                with open(f"/proc/{pid}/task/{task}/children") as f:
                    todo.extend(int(c) for c in f.read().split())
            except OSError:
                continue  # the thread or process ended
    return pids


class TreeMemory:
    """Samples the resident memory of this process and its descendants."""

    def __init__(self, period_s: float = 0.5):
        self.period_s = period_s
        self._root = psutil.Process()
        self._stop = threading.Event()
        self._lock = threading.Lock()
        self.total_peak_mb = 0.0
        self.peak_by_process: dict[int, tuple[str, float]] = {}  # pid -> (name, peak MB)
        self._thread = threading.Thread(target=self._run, name="memory", daemon=True)

    def start(self) -> TreeMemory:
        self._thread.start()
        return self

    def _run(self) -> None:
        while not self._stop.wait(self.period_s):
            self.sample()

    def sample(self) -> None:
        pids = _tree_pids(self._root.pid)
        if pids is None:
            try:
                pids = [self._root.pid, *(c.pid for c in self._root.children(recursive=True))]
            except psutil.Error:
                return
        total = 0.0
        for pid in pids:
            status = _status(pid)
            if status is None:
                continue
            name, rss_mb, peak_mb = status
            name = "main" if pid == self._root.pid else name
            total += rss_mb
            peak = max(peak_mb, rss_mb)
            with self._lock:
                _, before = self.peak_by_process.get(pid, (name, 0.0))
                # max over samples too: a spawned worker's peak restarts at its exec, while
                # its sample just before (the forked copy of this process) counted in a total
                self.peak_by_process[pid] = (name, max(peak, before))
        with self._lock:
            self.total_peak_mb = max(self.total_peak_mb, total)

    def stop(self) -> None:
        self.sample()
        self._stop.set()

    def summary(self, names: dict[int, str] | None = None) -> dict[str, Any]:
        """stats.json ``memory``: the tree's total at its (sampled) peak and each process's
        own peak, named by role where ``names`` (pid -> role) says."""
        names = names or {}
        with self._lock:
            per = {
                f"{names.get(pid, name)} ({pid})": round(mb, 1)
                for pid, (name, mb) in sorted(self.peak_by_process.items())
            }
            total = self.total_peak_mb
        return {
            "total_peak_mb": round(total, 1),
            "sum_of_process_peaks_mb": round(sum(per.values()), 1),
            "per_process_peak_mb": per,
            "sample_period_s": self.period_s,
        }

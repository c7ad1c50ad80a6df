"""Memory of the whole process tree: the main process and every worker it started.

``ru_maxrss`` gives one process's peak only (and ``RUSAGE_CHILDREN`` only children that have
ended and been waited for), so a sampler thread reads the tree's resident sizes every
``period_s`` with psutil: each process's own peak comes from the kernel (``VmHWM``, exact),
the total at its peak from the samples (the tree's sum can peak between two samples). Resident
sizes count pages shared between processes (the reader's image ring, a worker just forked) in
each of them.
"""

from __future__ import annotations

import threading
from typing import Any

import psutil


def _peak_mb(proc: psutil.Process) -> float | None:
    """The kernel's peak resident size of ``proc`` (Linux VmHWM), else its current one."""
    try:
        with open(f"/proc/{proc.pid}/status") as f:
            for line in f:
                if line.startswith("VmHWM:"):
                    return int(line.split()[1]) / 1024.0  # kB
    except OSError:
        pass
    try:
        return float(proc.memory_info().rss) / 2**20
    except psutil.Error:
        return None


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
        try:
            procs = [self._root, *self._root.children(recursive=True)]
        except psutil.Error:
            return
        total = 0.0
        for proc in procs:
            try:
                rss_mb = proc.memory_info().rss / 2**20
                name = proc.name() if proc is not self._root else "main"
            except psutil.Error:
                continue
            total += rss_mb
            peak = max(_peak_mb(proc) or 0.0, rss_mb)
            with self._lock:
                _, before = self.peak_by_process.get(proc.pid, (name, 0.0))
                # max over samples too: a spawned worker's peak restarts at its exec, while
                # its sample just before (the forked copy of this process) counted in a total
                self.peak_by_process[proc.pid] = (name, max(peak, before))
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

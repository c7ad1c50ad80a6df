"""Where a thread's wall time goes: its CPU time, and its wait on the OS run queue.

A front-end frame that takes longer than its CPU time waited for something: the GIL (another
thread of this process ran Python), or a CPU (the thread was runnable but the scheduler ran
another process). Linux counts the second per thread in ``/proc/thread-self/schedstat``
(second field, ns); the rest of the wait is the GIL or sleeping. This split is what showed that
the front end's p99 on 2 cores was run-queue wait behind the worker processes, not the GIL.
"""

from __future__ import annotations

import time

_SCHEDSTAT = "/proc/thread-self/schedstat"


def thread_cpu_s() -> float:
    """CPU time of the calling thread (s)."""
    return time.thread_time()


def runqueue_wait_ns() -> int | None:
    """Total time the calling thread has spent runnable but not running (ns), or None where
    the OS does not report it (not Linux, or a kernel without schedstats)."""
    try:
        with open(_SCHEDSTAT, "rb") as fh:
            fields = fh.read().split()
        return int(fields[1])
    except (OSError, IndexError, ValueError):
        return None


_PROC_STAT = "/proc/stat"


def machine_cpu_ticks() -> tuple[int, int, int] | None:
    """The whole machine's CPU time so far, in clock ticks (all CPUs): (busy, idle, steal), or
    None where the OS does not say (not Linux). Steal is time the hypervisor ran something else
    on a virtual CPU that had work. It is in neither a thread's CPU time nor its run-queue wait
    (Linux's paravirtual steal accounting takes it out of both), so in a front-end frame it
    shows in the rest, ``frontend_frame_gil``: on this project's 2-vCPU VM frames that held a
    steal tick had a rest of 4.9 ms on average against 1.4 ms (BENCHMARKS.md, "Front end's
    p99 with the mapper: stopped during frames")."""
    try:
        with open(_PROC_STAT, "rb") as fh:
            fields = [int(v) for v in fh.readline().split()[1:]]
    except (OSError, ValueError):
        return None
    if len(fields) < 8:
        return None
    user, nice, system, idle, iowait, irq, softirq, steal = fields[:8]
    return user + nice + system + irq + softirq, idle + iowait, steal


def machine_cpu_since(start: tuple[int, int, int] | None) -> dict[str, float] | None:
    """Shares of the machine's CPU time since ``start`` (:func:`machine_cpu_ticks`): busy (any
    process), idle and stolen by the hypervisor; None if unknown or no time passed."""
    now = machine_cpu_ticks()
    if start is None or now is None:
        return None
    busy, idle, steal = (b - a for a, b in zip(start, now, strict=True))
    total = busy + idle + steal
    if total <= 0:
        return None
    return {
        "busy_fraction": busy / total,
        "idle_fraction": idle / total,
        "steal_fraction": steal / total,
    }

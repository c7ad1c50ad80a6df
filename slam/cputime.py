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

"""Thread CPU time and run-queue wait (the split of a front-end frame's latency)."""

from __future__ import annotations

import sys
import threading

import pytest

from slam.cputime import runqueue_wait_ns, thread_cpu_s


def _spin(n: int) -> int:
    total = 0
    for i in range(n):
        total += i * i
    return total


def test_thread_cpu_time_counts_only_the_calling_thread() -> None:
    t0 = thread_cpu_s()
    _spin(300_000)
    busy = thread_cpu_s() - t0
    assert busy > 0.001
    # another thread's work is not ours
    t1 = thread_cpu_s()
    worker = threading.Thread(target=_spin, args=(300_000,))
    worker.start()
    worker.join()
    assert thread_cpu_s() - t1 < 0.5 * busy


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="schedstat is Linux-only")
def test_runqueue_wait_is_a_non_decreasing_counter() -> None:
    a = runqueue_wait_ns()
    _spin(100_000)
    b = runqueue_wait_ns()
    assert a is not None and b is not None and 0 <= a <= b

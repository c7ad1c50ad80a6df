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
    # ~0.1 s of work each: starting and joining a thread costs the caller a few ms of CPU on
    # a loaded machine (5.7 ms against 10.6 ms of work, once, at 300,000)
    t0 = thread_cpu_s()
    _spin(3_000_000)
    busy = thread_cpu_s() - t0
    assert busy > 0.01
    # another thread's work is not ours
    t1 = thread_cpu_s()
    worker = threading.Thread(target=_spin, args=(3_000_000,))
    worker.start()
    worker.join()
    assert thread_cpu_s() - t1 < 0.5 * busy


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="schedstat is Linux-only")
def test_runqueue_wait_is_a_non_decreasing_counter() -> None:
    a = runqueue_wait_ns()
    _spin(100_000)
    b = runqueue_wait_ns()
    assert a is not None and b is not None and 0 <= a <= b


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="/proc/stat is Linux's")
def test_machine_cpu_shares_add_up_and_see_busy_work() -> None:
    from slam.cputime import machine_cpu_since, machine_cpu_ticks

    start = machine_cpu_ticks()
    assert start is not None and all(v >= 0 for v in start)
    _spin(3_000_000)  # a few clock ticks (10 ms each) of work on this CPU
    shares = machine_cpu_since(start)
    assert shares is not None
    assert sum(shares.values()) == pytest.approx(1.0)
    assert shares["busy_fraction"] > 0.0  # at least this process ran
    assert all(0.0 <= v <= 1.0 for v in shares.values())
    assert machine_cpu_since(None) is None

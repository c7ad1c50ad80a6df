"""Worker processes start at the priority they are given, before they run any of their code."""

from __future__ import annotations

import os
import queue
import threading

import pytest

from slam.messages import EndOfStream
from slam.worker import READY, WorkerProcess


def _report_priority(inbox, outbox) -> None:  # type: ignore[no-untyped-def]
    outbox.put(READY)
    # A thread started by the worker inherits the policy (the loop closer's and GTSAM's do).
    seen: list[int] = []
    t = threading.Thread(target=lambda: seen.append(os.sched_getscheduler(0)))
    t.start()
    t.join()
    outbox.put((os.sched_getscheduler(0), seen[0], os.getpriority(os.PRIO_PROCESS, 0)))
    while not isinstance(inbox.get(), EndOfStream):
        pass
    outbox.put("done")


def _priority_of(nice: int, idle: bool) -> tuple[int, int, int]:
    items: queue.Queue = queue.Queue()

    def on_item(item: object) -> bool:
        items.put(item)
        return item == "done"

    worker = WorkerProcess(
        "prio-test", _report_priority, (), on_item, lambda: None, 60.0, nice, idle
    )
    try:
        return items.get(timeout=60)
    finally:
        worker.stop(receive_timeout_s=30)


@pytest.mark.skipif(not hasattr(os, "SCHED_IDLE"), reason="SCHED_IDLE is Linux-only")
def test_idle_worker_runs_under_sched_idle_with_its_nice_level() -> None:
    base = os.getpriority(os.PRIO_PROCESS, 0)
    policy, thread_policy, nice = _priority_of(7, idle=True)
    assert policy == os.SCHED_IDLE and thread_policy == os.SCHED_IDLE
    assert nice == min(base + 7, 19)


@pytest.mark.skipif(not hasattr(os, "SCHED_IDLE"), reason="SCHED_IDLE is Linux-only")
def test_normal_worker_keeps_the_normal_policy() -> None:
    base = os.getpriority(os.PRIO_PROCESS, 0)
    policy, thread_policy, nice = _priority_of(19, idle=False)
    assert policy == os.SCHED_OTHER and thread_policy == os.SCHED_OTHER
    assert nice == 19 or base >= 19

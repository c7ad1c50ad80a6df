"""Scheduling priorities of a run's processes and threads (Linux; elsewhere nothing changes).

One table says how much each part of the pipeline yields to the others. The front end answers
every frame and keeps the normal priority; the reader is on the data path and must never
starve; the back end must stay fresh; loop closure and the mapper only have to keep up on
average. Why these numbers, measured beside busy processes: BENCHMARKS.md ("Priorities").

A process can only lower its own priority without privileges, never raise it back, so the
scheme is fixed at start. ``SCHED_IDLE`` gets almost no CPU while normal-priority work keeps
every core busy (measured: a real-time run beside two busy processes processed 21 s of a 115 s
sequence in 827 s, its SCHED_IDLE reader starved), so by default only the mapper's live work
uses it (``mapping.idle_worker``: what it does not fuse live is caught up at the end, and a
core running only SCHED_IDLE work counts as idle to a waking front end);
``player.idle_workers: true`` puts the loop worker under it too, on a machine that is known to
be otherwise idle.
"""

from __future__ import annotations

import os
import signal

from threadpoolctl import threadpool_limits

ROLE_NICE: dict[str, int] = {
    "frontend": 0,
    "reader": 0,
    "backend": 2,
    "loop": 10,
    "mapper": 15,
}
"""Nice level added to each role's live work (the front end's is the main process's; a
worker's end-of-run work runs at full priority, ``slam.runtime.worker``). Beside two busy
processes, room-aggressive in real time dropped 38 % of its frames with the loop worker at
nice 5, 9-15 % at nice 10."""

BLAS_THREADS = 1
"""Threads of the BLAS libraries (numpy's, scipy's, GTSAM's OpenBLAS) in each process of a run.
Their linear algebra is small (the monocular scale check's least squares of ~190 x 100, batched
4x4 SVDs), and each process had a pool of its own, one thread per core, spinning while it
waits: beside a run's other processes a 189 x 102 ``lstsq`` took 97 ms of CPU (391 ms wall)
with OpenBLAS's two threads, 2.2 ms with one, and the monocular back end spent most of its
CPU there (BENCHMARKS.md, monospeed18)."""

IDLE_ROLES = frozenset({"loop", "mapper"})
"""Roles that run under SCHED_IDLE when ``player.idle_workers`` is set."""


def lower_priority(increment: int, idle: bool = False) -> None:
    """Lower the calling process's priority by ``increment`` nice levels; ``idle`` also puts it
    under ``SCHED_IDLE``. Threads it starts later inherit both. Errors (not permitted, not
    Linux) leave the priority as it was."""
    if increment > 0:
        try:
            os.nice(increment)
        except OSError:
            pass
    if idle and hasattr(os, "sched_setscheduler") and hasattr(os, "SCHED_IDLE"):
        try:
            os.sched_setscheduler(0, os.SCHED_IDLE, os.sched_param(0))
        except OSError:
            pass


def apply_role(role: str, idle_workers: bool = False) -> None:
    """Give the calling thread (and the threads it starts) its role's priority (on Linux,
    nice levels and scheduling policies are per thread)."""
    lower_priority(ROLE_NICE.get(role, 0), idle_workers and role in IDLE_ROLES)


def limit_blas_threads(threads: int = BLAS_THREADS) -> threadpool_limits:
    """Limit the BLAS libraries loaded in this process to ``threads`` (:data:`BLAS_THREADS`);
    the limits hold until the returned object's ``restore_original_limits()`` (or the end of
    its ``with`` block). Libraries loaded later keep their own setting: call it once the
    process's imports are done."""
    return threadpool_limits(limits=threads, user_api="blas")


def ignore_stop_signals() -> None:
    """In a worker process: leave SIGINT and SIGTERM to the main process.

    Ctrl-C in a terminal sends SIGINT to every process of the foreground group; a worker that
    died of it would lose its results (and print a traceback). The main process ends the
    workers in order instead; a worker whose main process dies ends by itself
    (:func:`slam.runtime.worker.main_process_gone`).
    """
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_IGN)

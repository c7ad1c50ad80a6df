"""A stage's worker process: spawned, waited for, fed through an inbox, read by a receiver.

GTSAM holds the GIL for whole calls and the mapper's numpy work is heavy, so the back end, the
loop closer and the mapper each run in a worker process. This is their common plumbing: spawn
(threads are running, so no fork), wait until the worker says ``"ready"`` (so real-time playback
does not start against a worker still importing GTSAM), a receiver thread that hands every
item from the outbox to the stage and notices a worker that died, and an orderly stop.

The worker function takes ``(*args, inbox, outbox)``, puts ``"ready"`` once it can work, ends
on :class:`EndOfStream`.
"""

from __future__ import annotations

import multiprocessing as mp
import os
import queue
import threading
from collections.abc import Callable
from typing import Any

from slam.messages import EndOfStream

READY = "ready"


def lower_priority(increment: int, idle: bool = False) -> None:
    """Lower the calling process's priority: a worker only has to keep up on average, the front
    end must answer every frame.

    ``increment`` is added to its nice level. ``idle`` also puts it under Linux's ``SCHED_IDLE``
    policy (ignored where the OS lacks it): it then gets whatever CPU the normal-priority
    threads leave, and a front end that wakes up preempts it at once instead of waiting out a
    time slice. Nice levels alone do not do that: on 2 cores with the back-end, loop and reader
    processes at nice 5-10, the front end waited up to 27 ms (p99) per frame on the run queue
    (room-aggressive, ``--speed max``); under ``SCHED_IDLE`` 7 ms. Threads the process starts
    later inherit both. Errors (not permitted) leave the priority as it was.
    """
    try:
        os.nice(increment)
    except OSError:
        pass
    if idle and hasattr(os, "sched_setscheduler") and hasattr(os, "SCHED_IDLE"):
        try:
            os.sched_setscheduler(0, os.SCHED_IDLE, os.sched_param(0))
        except OSError:
            pass


def _run_lowered(target: Callable[..., None], increment: int, idle: bool, *args: Any) -> None:
    """A worker process's entry point: lower its priority before it starts any thread."""
    lower_priority(increment, idle)
    target(*args)


def main_process_gone() -> bool:
    """In a spawned child: has the process that started it died (the child was re-parented)?

    A killed main process (SIGKILL, OOM) cannot tell its children to stop; a child blocked on
    a queue or semaphore would wait forever, so it polls and asks this.
    """
    parent = mp.parent_process()
    return parent is not None and os.getppid() != parent.pid


def receive(inbox: Any, poll_s: float = 1.0) -> Any:
    """The next message of a worker's inbox; ends the worker if the main process has died."""
    while True:
        try:
            return inbox.get(timeout=poll_s)
        except queue.Empty:
            if main_process_gone():
                raise SystemExit(0) from None


class WorkerProcess:
    """One spawned worker and the thread that receives its output."""

    def __init__(
        self,
        name: str,
        target: Callable[..., None],
        args: tuple[Any, ...],
        on_item: Callable[[Any], bool],
        on_died: Callable[[], None],
        start_timeout_s: float = 120.0,
        nice: int = 0,
        idle: bool = False,
    ):
        """``on_item(item) -> True`` when it was the worker's last item; ``on_died()`` when the
        process ended without one. ``nice`` and ``idle``: see :func:`lower_priority`."""
        ctx = mp.get_context("spawn")
        self.inbox: Any = ctx.Queue()
        self.outbox: Any = ctx.Queue()
        self.proc = ctx.Process(
            target=_run_lowered,
            args=(target, nice, idle, *args, self.inbox, self.outbox),
            daemon=True,
            name=f"slam-{name}",
        )
        self.proc.start()
        try:
            ready = self.outbox.get(timeout=start_timeout_s)
        except queue.Empty:
            ready = None
        if ready != READY:
            self.proc.terminate()
            detail = f": {ready}" if isinstance(ready, Exception) else ""
            raise RuntimeError(f"the {name} worker process did not start{detail}")
        self._on_item = on_item
        self._on_died = on_died
        self.receiver = threading.Thread(target=self._receive, name=f"{name}-rx", daemon=True)
        self.receiver.start()

    def _receive(self) -> None:
        while True:
            try:
                item = self.outbox.get(timeout=0.5)
            except queue.Empty:
                if not self.proc.is_alive():
                    self._on_died()
                    return
                continue
            if self._on_item(item):
                return

    def put(self, msg: Any) -> None:
        self.inbox.put(msg)

    def is_alive(self) -> bool:
        return self.proc.is_alive()

    def stop(self, receive_timeout_s: float) -> None:
        """End of input: wait for the worker's last output, then for the process."""
        self.inbox.put(EndOfStream())
        self.receiver.join(timeout=receive_timeout_s)
        self.proc.join(timeout=10)
        self.terminate()

    def terminate(self) -> None:
        if self.proc.is_alive():
            self.proc.terminate()
        # Nobody will read what is still buffered for a dead worker: without this, the inbox's
        # feeder thread blocks the interpreter's exit on a full pipe (seen after a worker
        # failure: `slam run` printed its outputs, then hung).
        self.inbox.cancel_join_thread()

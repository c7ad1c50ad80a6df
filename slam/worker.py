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


def lower_priority(increment: int) -> None:
    """Nice the calling process: a worker only has to keep up on average, the front end must
    answer every frame (not permitted here: run at normal priority)."""
    try:
        os.nice(increment)
    except OSError:
        pass


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
    ):
        """``on_item(item) -> True`` when it was the worker's last item; ``on_died()`` when the
        process ended without one."""
        ctx = mp.get_context("spawn")
        self.inbox: Any = ctx.Queue()
        self.outbox: Any = ctx.Queue()
        self.proc = ctx.Process(
            target=target, args=(*args, self.inbox, self.outbox), daemon=True, name=f"slam-{name}"
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

"""The process-backed stage: a stage whose work runs in a worker process, or inline.

GTSAM holds the GIL for whole calls and the mapper's numpy work is heavy, so the back end, the
loop closer and the mapper each run their :class:`WorkerCore` in a spawned worker process in
concurrent runs (threads are running, so no fork), and inline in sequential runs: the same code
either way. One typed protocol (``slam.core.messages``): the worker sends :class:`WorkerReady` once
it can work, any outputs, and after :class:`EndOfStream` a :class:`WorkerFinal` with what the
stage returns at the end, or :class:`WorkerFailed` and ends. A worker that ends without either
died: that is an error of its own. Before end work that may overrun its time budget (the
global adjustment: its first iteration cannot be cut), a worker can send a
:class:`WorkerFallback`: the stage stops waiting for it at its time and ends with that.
"""

from __future__ import annotations

import copy
import multiprocessing as mp
import os
import queue
import signal
import threading
import time
import traceback
from abc import ABC, abstractmethod
from collections.abc import Callable
from typing import Any

from slam.core.messages import (
    EndOfStream,
    WorkerFailed,
    WorkerFallback,
    WorkerFinal,
    WorkerReady,
)
from slam.runtime.priority import apply_role, ignore_stop_signals, limit_blas_threads
from slam.runtime.stage import Stage, StageError


class WorkerDied(RuntimeError):
    """A worker process ended without its final message (killed, out of memory, a crash in
    native code)."""


class WorkerCore(ABC):
    """The part of a stage that may run in a worker process: messages in, outputs out."""

    end_began_s: float | None = None
    """``time.perf_counter()`` when the run's end began: the front end's last frame
    (``EndOfStream.run_end_began_s``), else when the worker was told to end, so :meth:`finish`
    counts the backlog (the stage's queue and the worker's) against a time budget. None
    when nobody said."""

    offer_fallback: Callable[[Any, float], None] | None = None
    """Set in a worker process (None inline): ``offer_fallback(payload, use_after_s)`` sends a
    :class:`WorkerFallback` from :meth:`finish`, before work that may overrun its time."""

    @abstractmethod
    def handle(self, msg: Any) -> list[Any]:
        """Outputs for one input message (sent back to the stage in order)."""

    def finish(self, interrupted: bool) -> Any:
        """What the stage gets at the end (``interrupted``: skip optional work)."""
        return None


def main_process_gone() -> bool:
    """In a spawned child: has the process that started it died (the child was re-parented)?

    A killed main process (SIGKILL, OOM) cannot tell its children to stop; a child blocked on
    a queue or semaphore would wait forever, so it polls and asks this.
    """
    parent = mp.parent_process()
    return parent is not None and os.getppid() != parent.pid


def name_this_process(name: str) -> None:
    """Give the calling process (from its main thread) a name in the kernel: ``/proc/PID/comm``,
    what ``top``, ``ps -o comm`` and stats.json ``memory`` show (at most 15 bytes) instead of
    "python". Linux's ``prctl(PR_SET_NAME)`` through ctypes: the standard library has no call
    for it, and a package (setproctitle) for one call is not worth a dependency. Elsewhere
    nothing changes."""
    try:
        import ctypes

        ctypes.CDLL(None).prctl(15, name.encode()[:15], 0, 0, 0)  # 15: PR_SET_NAME
    except (OSError, AttributeError):
        pass


def die_with_parent() -> None:
    """Linux: have the kernel kill the calling process (SIGKILL) when the thread that started it
    ends. A worker that the stage may stop (:meth:`WorkerProcess.pause`) cannot poll
    :func:`main_process_gone` while it is stopped; a main process killed at that moment would
    leave it stopped forever. Elsewhere nothing changes."""
    try:
        import ctypes

        ctypes.CDLL(None).prctl(1, int(signal.SIGKILL), 0, 0, 0)  # 1: PR_SET_PDEATHSIG
    except (OSError, AttributeError):
        pass
    if main_process_gone():  # it died before the call
        raise SystemExit(0)


def receive(inbox: Any, poll_s: float = 1.0) -> Any:
    """The next message of a worker's inbox; ends the worker if the main process has died."""
    while True:
        try:
            return inbox.get(timeout=poll_s)
        except queue.Empty:
            if main_process_gone():
                raise SystemExit(0) from None


def _failed(exc: BaseException) -> WorkerFailed:
    return WorkerFailed(f"{type(exc).__name__}: {exc}", traceback.format_exc())


def _worker_main(
    make_core: Callable[..., WorkerCore],
    args: tuple[Any, ...],
    role: str,
    idle: bool,
    inbox: Any,
    outbox: Any,
    hurry: Any,
    ending: Any,
    pausable: bool = False,
) -> None:
    """A worker process: build the core, answer every message, finish on EndOfStream.

    The live work runs in a thread at the role's priority (``slam.runtime.priority``: Linux
    priorities are per thread, and threads it starts inherit them). Once the run ends
    (``ending``, an event), this main thread takes over at the process's own priority: it
    drains the backlog and runs :meth:`WorkerCore.finish` (the global adjustment, the mesh),
    since the front end has finished by then. An unprivileged process cannot raise a priority
    it has lowered: measured beside two busy processes with the loop worker at nice 10
    throughout, the end of room-aggressive took 226 s. ``hurry`` (an event): the run was
    interrupted; skip the backlog and finish at once. ``pausable``: the stage may stop it
    (:func:`die_with_parent`).
    """
    ignore_stop_signals()
    if pausable:
        die_with_parent()
    name_this_process(f"slam-{role}")
    try:
        core = make_core(*args)
    except Exception as exc:
        outbox.put(_failed(exc))
        return
    limit_blas_threads()  # for the process's life; after the core's imports
    outbox.put(WorkerReady(os.getpid()))
    ended: list[bool] = []  # [interrupted] once EndOfStream arrived
    failed: list[bool] = []

    def step(msg: Any) -> bool:
        """Handle one message; True when the worker's input is over (or it failed)."""
        if isinstance(msg, EndOfStream):
            ended.append(msg.interrupted)
            if msg.run_end_began_s is not None and core.end_began_s is not None:
                core.end_began_s = min(core.end_began_s, msg.run_end_began_s)
            return True
        if hurry.is_set():
            return False
        try:
            for out in core.handle(msg):
                outbox.put(out)
        except Exception as exc:
            outbox.put(_failed(exc))
            failed.append(True)
            return True
        return False

    handed_over: list[Any] = []  # a message taken after the end began: the main thread's

    def serve() -> None:
        apply_role(role, idle)
        while not ending.is_set():
            try:
                msg = inbox.get(timeout=0.2)
            except queue.Empty:
                if main_process_gone():
                    return
                continue
            if ending.is_set():
                handed_over.append(msg)
                return
            if step(msg):
                return

    live = threading.Thread(target=serve, name="live")
    live.start()
    live.join()
    core.end_began_s = time.perf_counter()
    if handed_over:
        step(handed_over[0])
    while not ended and not failed:  # the end of the run: the backlog, at full priority
        step(receive(inbox))
    if failed:
        return

    def offer_fallback(payload: Any, use_after_s: float) -> None:
        # A copy: the queue pickles in its feeder thread, after the work that follows has
        # begun changing the core's state.
        outbox.put(WorkerFallback(copy.deepcopy(payload), use_after_s))

    core.offer_fallback = offer_fallback
    try:
        final = core.finish(ended[0] or hurry.is_set())
    except Exception as exc:
        outbox.put(_failed(exc))
        return
    outbox.put(WorkerFinal(final))


class WorkerProcess:
    """One spawned worker and the thread that receives its output."""

    def __init__(
        self,
        name: str,
        make_core: Callable[..., WorkerCore],
        args: tuple[Any, ...],
        on_item: Callable[[Any], bool],
        on_died: Callable[[int | None], None],
        role: str,
        idle: bool = False,
        start_timeout_s: float = 120.0,
        pausable: bool = False,
    ):
        """``on_item(item) -> True`` for the worker's last item; ``on_died(exit code)`` when the
        process ended without one; ``pausable``: :meth:`pause` may be used (the worker dies with
        the thread that starts it here, see :func:`die_with_parent`)."""
        ctx = mp.get_context("spawn")
        self.name = name
        self.inbox: Any = ctx.Queue()
        self.outbox: Any = ctx.Queue()
        self.hurry: Any = ctx.Event()
        self.ending: Any = ctx.Event()
        self.proc = ctx.Process(
            target=_worker_main,
            args=(
                make_core,
                args,
                role,
                idle,
                self.inbox,
                self.outbox,
                self.hurry,
                self.ending,
                pausable,
            ),
            daemon=True,
            name=f"slam-{name}",
        )
        self.proc.start()  # it imports and builds its core while the caller goes on
        self.pid: int | None = None
        self._start_timeout_s = start_timeout_s
        self._on_item = on_item
        self._on_died = on_died

    def wait_ready(self) -> None:
        """Wait for the worker's :class:`WorkerReady` (once; workers started one after the
        other start up side by side) and start receiving its outputs."""
        if self.pid is not None:
            return
        name = self.name
        first: Any = None
        deadline = time.monotonic() + self._start_timeout_s
        while first is None and time.monotonic() < deadline:
            try:
                first = self.outbox.get(timeout=0.5)
            except queue.Empty:
                if not self.proc.is_alive():
                    break
        if not isinstance(first, WorkerReady):
            self.terminate()
            detail = f": {first.error}" if isinstance(first, WorkerFailed) else ""
            raise RuntimeError(f"the {name} worker process did not start{detail}")
        self.pid = first.pid
        self.receiver = threading.Thread(target=self._receive, name=f"{name}-rx", daemon=True)
        self.receiver.start()

    def _receive(self) -> None:
        while True:
            try:
                item = self.outbox.get(timeout=0.5)
            except queue.Empty:
                if not self.proc.is_alive():
                    self._on_died(self.proc.exitcode)
                    return
                continue
            if self._on_item(item):
                return

    def put(self, msg: Any) -> None:
        self.wait_ready()  # a stage used before it was started
        self.inbox.put(msg)

    def begin_end(self) -> None:
        """The run is over: the worker's main thread takes over at full priority."""
        self.ending.set()

    def pause(self) -> bool:
        """Stop the whole process (SIGSTOP: every thread, inside native calls too) until
        :meth:`resume`; True if it was stopped. For a worker started ``pausable``. Keep it short
        and always resume: while stopped it may hold the lock of one of its events
        (``ending``, ``hurry``), so the caller must not end it in between."""
        if self.pid is None:
            return False
        try:
            os.kill(self.pid, signal.SIGSTOP)
        except OSError:  # already gone
            return False
        return True

    def resume(self) -> None:
        """Undo :meth:`pause` (SIGCONT)."""
        if self.pid is not None:
            try:
                os.kill(self.pid, signal.SIGCONT)
            except OSError:
                pass

    def is_alive(self) -> bool:
        return self.proc.is_alive()

    def stop(
        self,
        interrupted: bool,
        timeout_s: float,
        abandon: threading.Event | None,
        end_began_s: float | None = None,
        give_up: Callable[[], bool] | None = None,
    ) -> bool:
        """End of input: wait up to ``timeout_s`` (or until ``abandon`` is set, or ``give_up()``
        says so) for the worker's last output, then end the process. False when it had to be
        terminated. ``end_began_s``: ``EndOfStream.run_end_began_s``."""
        if self.pid is None:  # never waited for: nothing of it was used
            self.terminate()
            return False
        if interrupted:
            self.hurry.set()
        self.begin_end()
        self.inbox.put(EndOfStream(interrupted=interrupted, run_end_began_s=end_began_s))
        deadline = time.monotonic() + timeout_s
        while self.receiver.is_alive() and time.monotonic() < deadline:
            if abandon is not None and abandon.is_set():
                break
            if give_up is not None and give_up():
                break
            self.receiver.join(timeout=0.1)
        finished = not self.receiver.is_alive()
        if finished:
            self.proc.join(timeout=5)
        self.terminate()
        return finished

    def terminate(self) -> None:
        """End the process now (SIGKILL: a worker ignores SIGTERM, see
        :func:`slam.runtime.priority.ignore_stop_signals`)."""
        if self.proc.is_alive():
            self.proc.kill()
            self.proc.join(timeout=2)
        # Nobody will read what is still buffered for a dead worker: without this, the inbox's
        # feeder thread blocks the interpreter's exit on a full pipe (seen after a worker
        # failure: `slam run` printed its outputs, then hung).
        self.inbox.cancel_join_thread()


class ProcessStage(Stage):
    """A stage whose :class:`WorkerCore` runs in a worker process (concurrent runs, unless
    ``in_process`` is False) or inline in the stage's own thread.

    Subclasses implement :meth:`process` (what to send, with :meth:`send`), :meth:`on_output`
    and :meth:`on_final`. Ends: :meth:`end_worker` (called from ``on_end`` unless a subclass
    defers it) waits at most ``end_timeout_s`` for the final item.
    """

    end_timeout_s = 120.0

    def __init__(
        self,
        name: str,
        maxsize: int,
        threaded: bool,
        make_core: Callable[..., WorkerCore],
        args: tuple[Any, ...],
        *,
        role: str,
        in_process: bool = True,
        idle: bool = False,
        pausable: bool = False,
    ):
        """``pausable``: the worker may be stopped for a while (:meth:`WorkerProcess.pause`)."""
        super().__init__(name, maxsize=maxsize, threaded=threaded)
        self.use_process = threaded and in_process
        self.final_seen = threading.Event()
        self.timed_out = False
        self.fallback: WorkerFallback | None = None
        self.fallback_used = False  # the worker was stopped and the stage ended with it
        self._stopped_for_fallback = False
        self._final_lock = threading.Lock()  # one final: the worker's or the fallback
        self.worker_pid: int | None = None
        self._proc: WorkerProcess | None = None
        self._core: WorkerCore | None = None
        if self.use_process:
            self._proc = WorkerProcess(
                name, make_core, args, self._on_item, self._on_died, role, idle, pausable=pausable
            )
        else:
            self._core = make_core(*args)

    def start(self) -> None:
        if self._proc is not None:
            self._proc.wait_ready()
            self.worker_pid = self._proc.pid
        super().start()

    # -- to implement ------------------------------------------------------------------------
    def on_output(self, item: Any) -> None:
        """One output of the core (in the receiver thread, or inline)."""

    def on_final(self, payload: Any) -> None:
        """The core's final payload."""

    # -- plumbing ----------------------------------------------------------------------------
    def send(self, msg: Any) -> None:
        """Hand a message to the core (its outputs come back through :meth:`on_output`)."""
        if self._proc is not None:
            self._proc.put(msg)
            return
        assert self._core is not None
        for out in self._core.handle(msg):
            self._on_item(out)

    def _on_item(self, item: Any) -> bool:
        if isinstance(item, WorkerFailed):
            if self.error is None:
                self.error = StageError(self.name, RuntimeError(item.error), item.trace)
            self.final_seen.set()
            return True
        if isinstance(item, WorkerFinal):
            with self._final_lock:
                if not self.final_seen.is_set():
                    self.on_final(item.payload)
                    self.final_seen.set()
            return True
        if isinstance(item, WorkerFallback):
            self.fallback = item
            return False
        self.on_output(item)
        return False

    def _on_died(self, exit_code: int | None) -> None:
        if self._stopped_for_fallback:
            return  # stopped on purpose: :meth:`end_worker` ends the stage with the fallback
        if not self.final_seen.is_set() and self.error is None:
            self.error = StageError(
                self.name,
                WorkerDied(f"the {self.name} worker process died (exit code {exit_code})"),
                "",
            )
        self.final_seen.set()

    def on_end(self) -> None:
        self.end_worker()

    def begin_end(self) -> None:
        """The run is over: what the worker does from now on is end-of-run work (full priority)."""
        if self._proc is not None:
            self._proc.begin_end()

    def end_worker(self) -> None:
        """Send the end of input and take the final item (bounded by ``end_timeout_s``)."""
        if self.final_seen.is_set():
            return
        if self._proc is None:
            assert self._core is not None
            self._core.end_began_s = self.end_began_s
            self._on_item(WorkerFinal(self._core.finish(self.interrupted)))
            return
        timeout = self.end_timeout_s
        if not self._proc.stop(
            self.interrupted, timeout, self.abandon, self.end_began_s, self._fallback_due
        ):
            with self._final_lock:
                if self.final_seen.is_set():  # it came as the worker was stopped
                    return
                if self.fallback is not None:
                    self.on_final(self.fallback.payload)
                    self.fallback_used = True
                    self.final_seen.set()
                    return
            self.timed_out = True
            if self.error is None and not self.interrupted:
                self.error = StageError(
                    self.name,
                    RuntimeError(f"the {self.name} worker did not finish within {timeout:.0f} s"),
                    "",
                )
        self.final_seen.set()

    def _fallback_due(self) -> bool:
        """Stop waiting for the worker's final: its fallback's time has passed."""
        due = self.fallback is not None and time.perf_counter() > self.fallback.use_after_s
        self._stopped_for_fallback |= due
        return due

    def abort(self) -> None:
        super().abort()
        if self._proc is not None:
            self._proc.terminate()

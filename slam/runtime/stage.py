"""The pipeline stage: one loop, one bounded input queue, timing, error capture, shutdown.

A stage implements ``process(msg)`` and hands what it makes to the stages the wiring connected
to it (:meth:`Stage.connect`, :meth:`Stage.emit`): stages never read each other's state.
Concurrent mode runs it in its own thread, fed through a
bounded queue and ended by an :class:`EndOfStream` sentinel. Sequential mode (``threaded=False``)
calls ``process`` directly from ``put``, so the whole pipeline runs depth-first in one thread in
time order: deterministic, for tests and debugging. Both modes run the same code.
"""

from __future__ import annotations

import logging
import queue
import threading
import time
import traceback
from abc import ABC, abstractmethod
from typing import Any, Protocol

from slam.core.latency import latency_summary
from slam.core.messages import EndOfStream

log = logging.getLogger(__name__)


class StageError(RuntimeError):
    """An exception inside a stage, re-raised by the pipeline with the stage's name."""

    def __init__(self, stage: str, exc: BaseException, trace: str):
        super().__init__(f"stage '{stage}' failed: {type(exc).__name__}: {exc}")
        self.stage = stage
        self.exc = exc
        self.trace = trace


class Consumer(Protocol):
    """Anything a stage can hand messages to (a stage, the recorder)."""

    def put(self, msg: Any, block: bool = True) -> bool: ...


class Stage(ABC):
    """Base class of every pipeline stage."""

    def __init__(self, name: str, maxsize: int, threaded: bool):
        self.name = name
        self.interrupted = False  # the run was stopped: skip queued input and optional end work
        self.abandon: threading.Event | None = None  # set: stop waiting for anything, now
        self._consumers: list[tuple[Consumer, bool, tuple[type, ...]]] = []
        self.threaded = threaded
        self.queue: queue.Queue[Any] = queue.Queue(maxsize=maxsize)
        self.latencies_ms: list[float] = []
        self.error: StageError | None = None
        self.dropped = 0
        self.ended = threading.Event()
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()
        self.end_began_s: float | None = None  # EndOfStream.run_end_began_s, once it arrived

    # -- to implement ------------------------------------------------------------------------
    @abstractmethod
    def process(self, msg: Any) -> None:
        """Handle one message (may emit to downstream stages)."""

    def on_end(self) -> None:
        """Called once after the last message (flush, pass EndOfStream downstream)."""
        return None

    # -- connections -------------------------------------------------------------------------
    def connect(self, consumer: Consumer, *types: type, block: bool = True) -> None:
        """Hand every emitted message of ``types`` to ``consumer``, in connection order
        (``block`` False: the consumer may drop them, e.g. the viewer)."""
        self._consumers.append((consumer, block, types))

    def emit(self, msg: Any, block: bool | None = None) -> None:
        """Hand ``msg`` to every consumer connected for its type (``block`` overrides the
        connection's)."""
        for consumer, default, types in self._consumers:
            if isinstance(msg, types):
                consumer.put(msg, block=default if block is None else block)

    # -- plumbing ----------------------------------------------------------------------------
    def start(self) -> None:
        if self.threaded and self._thread is None:
            self._thread = threading.Thread(target=self._loop, name=self.name, daemon=True)
            self._thread.start()

    def put(self, msg: Any, block: bool = True) -> bool:
        """Hand a message to the stage. Returns False when it was dropped (queue full, no block)."""
        if self.error is not None:
            return False
        if not self.threaded:
            if isinstance(msg, EndOfStream):
                self.end_began_s = msg.run_end_began_s
                self._finish()
            else:
                self._handle(msg)
            return True
        try:
            self.queue.put(msg, block=block, timeout=None)
            return True
        except queue.Full:
            self.dropped += 1
            return False

    def close(self, timeout_s: float | None = None, end_began_s: float | None = None) -> bool:
        """Signal end of input (the sentinel gets through a full queue as the stage drains it;
        ``timeout_s``: give up after that long, e.g. for a viewer stuck in a call;
        ``end_began_s``: ``EndOfStream.run_end_began_s``). False when it gave up."""
        if not self.threaded:
            self.end_began_s = end_began_s
            self._finish()
            return True
        deadline = None if timeout_s is None else time.monotonic() + timeout_s
        while self._thread is not None and self._thread.is_alive():
            try:
                self.queue.put(EndOfStream(run_end_began_s=end_began_s), timeout=0.1)
                return True
            except queue.Full:
                if deadline is not None and time.monotonic() > deadline:
                    return False
        return True

    def interrupt(self) -> None:
        """The run was stopped (Ctrl-C, SIGTERM): skip queued input; ``on_end`` still runs, with
        :attr:`interrupted` set, so the stage's results so far are kept."""
        self.interrupted = True
        self._stop.set()

    def abort(self) -> None:
        """Stop as soon as possible, discarding queued input (another stage failed)."""
        self._stop.set()
        self.close()

    def join(self, timeout: float | None = None) -> bool:
        """Wait for the stage's thread; True when it has ended."""
        if self._thread is not None:
            self._thread.join(timeout)
            return not self._thread.is_alive()
        return True

    def _handle(self, msg: Any) -> None:
        t0 = time.perf_counter()
        try:
            self.process(msg)
        except Exception as exc:  # captured, reported with the stage name by the pipeline
            self.error = StageError(self.name, exc, traceback.format_exc())
            log.error("%s", self.error)
        self.latencies_ms.append((time.perf_counter() - t0) * 1e3)

    def _finish(self) -> None:
        if self.ended.is_set():
            return
        try:
            self.on_end()
        except Exception as exc:
            self.error = self.error or StageError(self.name, exc, traceback.format_exc())
        self.ended.set()

    def _loop(self) -> None:
        while True:
            msg = self.queue.get()
            if isinstance(msg, EndOfStream):
                self.end_began_s = msg.run_end_began_s
                break
            if self._stop.is_set() or self.error is not None:
                continue  # drain without work until the sentinel
            self._handle(msg)
        self._finish()

    def latency_stats(self) -> dict[str, float]:
        """p50/p90/p99/max of process() time in ms."""
        return latency_summary(self.latencies_ms)


class Latest:
    """An atomically swapped reference to the latest immutable snapshot (never waits)."""

    def __init__(self) -> None:
        self._value: Any = None

    def get(self) -> Any:
        return self._value

    def set(self, value: Any) -> None:
        self._value = value  # a single reference assignment is atomic under the GIL

"""How a run is stopped from outside: SIGINT (Ctrl-C) and SIGTERM.

The first signal stops reading: the player ends, every stage skips its queued input and ends
(the loop closer without its final adjustment), and every output is written for what was
processed. A second signal stops waiting for the stages: workers still busy are terminated and
the outputs are written from what has arrived. The exit code is 128 + the first signal's
number (130 for SIGINT, 143 for SIGTERM), the shell's convention.
"""

from __future__ import annotations

import signal
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from types import FrameType


class RunControl:
    """Set by the signal handlers, read by the player and the end of the run."""

    def __init__(self) -> None:
        self.stop = threading.Event()  # stop reading, end the stages in order
        self.abandon = threading.Event()  # stop waiting for the stages
        self.signal_number: int | None = None

    @property
    def exit_code(self) -> int:
        return 0 if self.signal_number is None else 128 + self.signal_number

    @property
    def signal_name(self) -> str:
        return "" if self.signal_number is None else signal.Signals(self.signal_number).name

    def request_stop(self, signum: int) -> None:
        if self.stop.is_set():
            self.abandon.set()
        else:
            self.signal_number = signum
            self.stop.set()


@contextmanager
def handle_stop_signals(control: RunControl) -> Iterator[RunControl]:
    """Route SIGINT and SIGTERM to ``control`` while the block runs (main thread only;
    elsewhere, e.g. a test's worker thread, signals keep their handlers)."""
    if threading.current_thread() is not threading.main_thread():
        yield control
        return

    def handler(signum: int, frame: FrameType | None) -> None:
        control.request_stop(signum)

    previous = {s: signal.signal(s, handler) for s in (signal.SIGINT, signal.SIGTERM)}
    try:
        yield control
    finally:
        for s, h in previous.items():
            signal.signal(s, h)

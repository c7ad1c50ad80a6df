"""A worker's fallback: end work that overruns its time (the global adjustment's first
iteration cannot be cut) is stopped, and the stage ends with the state sent before it."""

from __future__ import annotations

import time
from typing import Any

from slam.runtime.worker import ProcessStage, WorkerCore


class _SlowFinish(WorkerCore):
    """``finish`` offers "before" (to be used 1 s after the end began), then works for
    ``work_s`` and returns "after"."""

    def __init__(self, work_s: float):
        self.work_s = work_s

    def handle(self, msg: Any) -> list[Any]:
        return []

    def finish(self, interrupted: bool) -> Any:
        if self.offer_fallback is not None and self.end_began_s is not None:
            self.offer_fallback({"state": "before"}, self.end_began_s + 1.0)
        end = time.monotonic() + self.work_s
        while time.monotonic() < end:  # busy, like GTSAM holding the GIL: no checks inside
            sum(range(10_000))
        return {"state": "after"}


class _Stage(ProcessStage):
    def __init__(self, work_s: float, in_process: bool = True):
        super().__init__(
            "probe", 4, True, _SlowFinish, (work_s,), role="loop", in_process=in_process
        )
        self.final: Any = None

    def process(self, msg: Any) -> None:
        self.send(msg)

    def on_final(self, payload: Any) -> None:
        self.final = payload


def _end(stage: _Stage) -> float:
    stage.start()
    began_s = time.perf_counter()
    stage.close(end_began_s=began_s)
    stage.join(120)
    return time.perf_counter() - began_s


def test_overrunning_end_work_is_stopped_and_the_fallback_used() -> None:
    stage = _Stage(work_s=60.0)
    took_s = _end(stage)
    assert stage.error is None and not stage.timed_out
    assert stage.final == {"state": "before"} and stage.fallback_used
    assert took_s < 20.0  # 1 s after the end began, plus polling and the worker's stop
    assert stage._proc is not None and not stage._proc.proc.is_alive()


def test_end_work_in_time_gives_the_real_final() -> None:
    stage = _Stage(work_s=0.0)
    _end(stage)
    assert stage.error is None
    assert stage.final == {"state": "after"} and not stage.fallback_used


def test_inline_core_is_offered_no_fallback() -> None:
    """Inline (sequential runs) nothing can stop the work: it runs to its end."""
    stage = _Stage(work_s=1.5, in_process=False)
    _end(stage)
    assert stage.final == {"state": "after"} and not stage.fallback_used

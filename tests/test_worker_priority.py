"""Worker processes run at their role's priority, set before they run any of their code, and
leave SIGINT/SIGTERM to the main process; their BLAS libraries run on ``BLAS_THREADS``."""

from __future__ import annotations

import contextlib
import os
import signal
import threading
import time
from typing import Any

import numpy as np
import pytest
from threadpoolctl import threadpool_info

from slam.runtime.priority import BLAS_THREADS, ROLE_NICE, limit_blas_threads
from slam.runtime.worker import ProcessStage, WorkerCore


class _ReportPriority(WorkerCore):
    def handle(self, msg: Any) -> list[Any]:
        # A thread started by the worker inherits the policy (the loop closer's and GTSAM's do).
        seen: list[int] = []
        t = threading.Thread(target=lambda: seen.append(os.sched_getscheduler(0)))
        t.start()
        t.join()
        return [
            (
                os.sched_getscheduler(0),
                seen[0],
                os.getpriority(os.PRIO_PROCESS, 0),
                signal.getsignal(signal.SIGINT) == signal.SIG_IGN,
            )
        ]


class _Probe(ProcessStage):
    def __init__(self, role: str, idle: bool, core: type[WorkerCore] = _ReportPriority):
        super().__init__("probe", 4, True, core, (), role=role, idle=idle)
        self.got: list[Any] = []

    def process(self, msg: Any) -> None:
        self.send(msg)

    def on_output(self, item: Any) -> None:
        self.got.append(item)


def _priority_of(role: str, idle: bool) -> tuple[int, int, int, bool]:
    return _answer(_Probe(role, idle))


def _answer(stage: _Probe) -> Any:
    stage.start()
    stage.put("report")
    deadline = time.monotonic() + 60
    while not stage.got and time.monotonic() < deadline:  # answered by the live thread: the
        time.sleep(0.05)  # end of the run would hand the backlog to the full-priority thread
    stage.close()
    stage.join(60)
    assert stage.error is None and stage.final_seen.is_set()
    return stage.got[0]


@pytest.mark.skipif(not hasattr(os, "SCHED_IDLE"), reason="SCHED_IDLE is Linux-only")
def test_idle_worker_runs_under_sched_idle_with_its_nice_level() -> None:
    base = os.getpriority(os.PRIO_PROCESS, 0)
    policy, thread_policy, nice, ignores_sigint = _priority_of("mapper", idle=True)
    assert policy == os.SCHED_IDLE and thread_policy == os.SCHED_IDLE
    assert nice == min(base + ROLE_NICE["mapper"], 19)
    assert ignores_sigint


@pytest.mark.skipif(not hasattr(os, "SCHED_IDLE"), reason="SCHED_IDLE is Linux-only")
def test_data_path_and_back_end_never_idle() -> None:
    """The reader and the back end keep the normal policy even with ``idle_workers``: under
    SCHED_IDLE they starve beside busy processes."""
    base = os.getpriority(os.PRIO_PROCESS, 0)
    for role in ("backend", "reader"):
        policy, thread_policy, nice, _ = _priority_of(role, idle=True)
        assert policy == os.SCHED_OTHER and thread_policy == os.SCHED_OTHER
        assert nice == min(base + ROLE_NICE[role], 19)


@pytest.mark.skipif(not hasattr(os, "SCHED_IDLE"), reason="SCHED_IDLE is Linux-only")
def test_end_of_run_work_runs_at_full_priority() -> None:
    """What the worker does once the run is over (its backlog, ``finish``) runs in its main
    thread, which kept the process's own priority."""
    stage = _Probe("mapper", idle=True)
    stage.start()
    stage.begin_end()
    stage.put("report")
    stage.close()
    stage.join(60)
    assert stage.error is None and stage.final_seen.is_set()
    policy, _, nice, _ = stage.got[0]
    assert policy == os.SCHED_OTHER
    assert nice == os.getpriority(os.PRIO_PROCESS, 0)


class _ReportEndBegan(WorkerCore):
    def handle(self, msg: Any) -> list[Any]:
        return []

    def finish(self, interrupted: bool) -> Any:
        return self.end_began_s


class _EndProbe(ProcessStage):
    def __init__(self, in_process: bool):
        super().__init__("probe", 4, True, _ReportEndBegan, (), role="loop", in_process=in_process)
        self.final: Any = None

    def process(self, msg: Any) -> None:
        self.send(msg)

    def on_final(self, payload: Any) -> None:
        self.final = payload


@pytest.mark.parametrize("in_process", [True, False])
def test_worker_counts_its_end_from_the_runs_end(in_process: bool) -> None:
    """A worker's end-of-run budget counts from when the run's end began (the front end's last
    frame, ``EndOfStream.run_end_began_s``), not from when the worker heard of it: the clock
    (``time.perf_counter``, CLOCK_MONOTONIC) is the same in the worker process."""
    stage = _EndProbe(in_process)
    stage.start()
    began_s = time.perf_counter() - 5.0  # the front end ended 5 s ago
    stage.close(end_began_s=began_s)
    stage.join(60)
    assert stage.error is None and stage.final_seen.is_set()
    assert stage.final == began_s


@pytest.mark.parametrize(
    ("mapper_idle", "idle_workers", "expected"),
    [(True, False, True), (False, False, False), (False, True, True)],
)
def test_live_mapper_is_sched_idle_unless_configured_otherwise(
    monkeypatch: pytest.MonkeyPatch, mapper_idle: bool, idle_workers: bool, expected: bool
) -> None:
    """The run's mapper stage gets ``idle_worker`` from ``mapping.idle_worker`` (default on: at
    nice +15 the mapper kept its core while the front end waited) or ``player.idle_workers``."""
    from dataclasses import replace

    from datasets.memory import random_sequence
    from slam.config import preset_config
    from slam.runtime import wiring

    seen: list[bool] = []

    class _Mapper:
        def __init__(self, *args: Any, **kw: Any) -> None:
            seen.append(args[3])
            self.pausable = kw["pausable"]

        def paused_while_working(self) -> Any:
            return contextlib.nullcontext()

    monkeypatch.setattr(wiring, "MapperStage", _Mapper)
    cfg = preset_config("stereo-vo")
    cfg.loop_closure = False
    cfg.player.idle_workers = idle_workers
    cfg.mapping = replace(cfg.mapping, enabled=True, idle_worker=mapper_idle)
    p = wiring.build(random_sequence(num_frames=3), cfg, None)
    assert seen == [expected]
    assert preset_config("stereo-vo").mapping.idle_worker  # the default
    # mapping.pause_while_tracking (default on): the front end's frames stop the mapper
    assert p.mapper is not None and p.mapper.pausable
    assert p.frontend.quiet == p.mapper.paused_while_working


@pytest.mark.parametrize(
    ("speed", "sequential", "pause", "expected"),
    [
        (1.0, False, True, True),
        (0.0, False, True, False),
        (1.0, True, True, False),
        (1.0, False, False, False),
    ],
)
def test_mapper_is_stopped_during_frames_only_in_paced_concurrent_runs(
    monkeypatch: pytest.MonkeyPatch, speed: float, sequential: bool, pause: bool, expected: bool
) -> None:
    """``mapping.pause_while_tracking`` applies at a paced speed in a concurrent run: at
    ``--speed max`` (0) the front end never rests, and a sequential run has no worker."""
    from dataclasses import replace

    from datasets.memory import random_sequence
    from slam.config import preset_config
    from slam.runtime import wiring

    class _Mapper:
        def __init__(self, *args: Any, **kw: Any) -> None:
            self.pausable = kw["pausable"] and args[2]  # threaded

        def paused_while_working(self) -> Any:
            return contextlib.nullcontext()

    monkeypatch.setattr(wiring, "MapperStage", _Mapper)
    cfg = preset_config("stereo-vo")
    cfg.loop_closure = False
    cfg.player.speed = speed
    cfg.player.sequential = sequential
    cfg.mapping = replace(cfg.mapping, enabled=True, pause_while_tracking=pause)
    p = wiring.build(random_sequence(num_frames=3), cfg, None)
    assert p.mapper is not None and p.mapper.pausable == expected
    assert (p.frontend.quiet is not contextlib.nullcontext) == expected


class _ReportBlas(WorkerCore):
    def handle(self, msg: Any) -> list[Any]:
        np.linalg.lstsq(np.eye(3), np.ones(3), rcond=None)  # numpy's BLAS is loaded and used
        return [_blas_threads()]


def _blas_threads() -> list[int]:
    return [lib["num_threads"] for lib in threadpool_info() if lib["user_api"] == "blas"]


def test_worker_blas_runs_on_blas_threads_and_the_main_process_gets_its_own_back() -> None:
    """The limit is the worker's own: the main process's BLAS keeps its threads, and a run's
    limit in the main process is undone at its end."""
    before = _blas_threads()
    in_worker = _answer(_Probe("backend", idle=False, core=_ReportBlas))
    assert in_worker and set(in_worker) == {BLAS_THREADS}
    assert _blas_threads() == before
    limits = limit_blas_threads()
    assert set(_blas_threads()) == {BLAS_THREADS}
    limits.restore_original_limits()
    assert _blas_threads() == before

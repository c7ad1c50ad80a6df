"""Who executes a batch's runs: this machine (``local``) or a Ray cluster (``ray``).

An engine gets the task list built by :func:`tools.batch.spec.build_tasks` and yields one
:class:`BatchOutcome` per task as runs finish, in any order; every task runs
:func:`tools.batch.task.execute`, which starts `slam run` in its own process. The engine only
decides where and how many at once, by the CPUs each run declares (``cpus_per_run``).
"""

from __future__ import annotations

import logging
import os
import socket
import threading
from collections.abc import Iterator
from concurrent.futures import FIRST_COMPLETED, Future, ThreadPoolExecutor, wait
from pathlib import Path
from typing import Any

from slam.core.errors import SlamError
from slam.core.messages import BatchOutcome, BatchTask
from tools.batch.task import execute

ENGINES = ("local", "ray")
RAY_MISSING = "--engine ray needs Ray, which is not installed: pip install '.[ray]'"


def failed(task: BatchTask, error: str) -> BatchOutcome:
    """The outcome of a task the engine could not run."""
    line = " ".join(error.split())[:500] or "failed"
    return BatchOutcome(task.run_id, False, line, {}, {}, 0.0, socket.gethostname())


class LocalEngine:
    """Runs on this machine: ``os.cpu_count() // cpus_per_run`` runs at once (at least one).

    Each run is its own `slam run` process; the pool's threads only start it, wait for it and
    measure it, so a thread pool is all the pool needs (no second layer of processes).
    """

    name = "local"

    def __init__(self, cpus_per_run: float, scratch_dir: Path, jobs: int | None = None) -> None:
        self.jobs = jobs or max(1, int((os.cpu_count() or 1) // max(cpus_per_run, 1e-9)))
        self.scratch_dir = scratch_dir
        self._stop = threading.Event()

    def run(self, tasks: list[BatchTask]) -> Iterator[BatchOutcome]:
        self.scratch_dir.mkdir(parents=True, exist_ok=True)
        with ThreadPoolExecutor(max_workers=self.jobs, thread_name_prefix="batch") as pool:
            pending: dict[Future[BatchOutcome], BatchTask] = {
                pool.submit(execute, t, self._stop, str(self.scratch_dir)): t for t in tasks
            }
            try:
                while pending:
                    done, _ = wait(pending, return_when=FIRST_COMPLETED)
                    for future in done:
                        task = pending.pop(future)
                        exc = future.exception()
                        yield (
                            failed(task, f"{type(exc).__name__}: {exc}") if exc else future.result()
                        )
            finally:  # stopped (Ctrl-C) or the caller went away: end the runs still going
                self._stop.set()
                for future in pending:
                    future.cancel()

    def close(self) -> None:
        self._stop.set()


class RayEngine:
    """Runs on an existing Ray cluster, each run a task declaring ``cpus_per_run`` CPUs.

    ``address``: ``auto`` (the cluster this machine is part of, started with `ray start`), a
    ``host:port`` of its head, or ``ray://host:10001`` (Ray Client). No cluster is ever started
    here: with no cluster at the address this is a one-line error. When the calling process has
    already called ``ray.init`` (tests: a local instance), that connection is used as it is.
    The workers run `python -m tools.cli run`: every node needs pyvislam installed, and the
    sequences at the path the task names (a shared folder, or ``path_map``).
    """

    name = "ray"

    def __init__(self, cpus_per_run: float, address: str = "auto") -> None:
        try:
            import ray
        except ImportError:
            raise SlamError(RAY_MISSING) from None
        self._ray: Any = ray
        self.cpus_per_run = cpus_per_run
        self._owned = False
        self._refs: dict[Any, BatchTask] = {}
        if not ray.is_initialized():
            try:
                ray.init(address=address, log_to_driver=False, logging_level=logging.WARNING)
            except (ConnectionError, ValueError, RuntimeError) as exc:
                first = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
                raise SlamError(
                    f"--address {address}: cannot join a Ray cluster ({first}); start one with "
                    "`ray start --head` (README: a two-node cluster; a cluster with token "
                    "authentication, Ray's default, also needs RAY_AUTH_MODE=token with an "
                    "explicit address)"
                ) from None
            self._owned = True

    def run(self, tasks: list[BatchTask]) -> Iterator[BatchOutcome]:
        ray = self._ray
        remote = ray.remote(execute).options(num_cpus=self.cpus_per_run, max_retries=0)
        self._refs = {remote.remote(t): t for t in tasks}
        try:
            while self._refs:
                done, _ = ray.wait(list(self._refs), num_returns=1)
                for ref in done:
                    task = self._refs.pop(ref)
                    try:
                        yield ray.get(ref)
                    except ray.exceptions.RayError as exc:  # the worker died, a node was lost
                        lines = str(exc).strip().splitlines()
                        yield failed(task, f"{type(exc).__name__}: {lines[-1] if lines else ''}")
        finally:
            for ref in self._refs:  # stopped: cancel what is queued or running
                ray.cancel(ref, force=True)

    def close(self) -> None:
        """Cancel what is still queued or running; disconnect (a joined cluster keeps running)."""
        for ref in self._refs:
            self._ray.cancel(ref, force=True)
        self._refs = {}
        if self._owned:
            self._ray.shutdown()
            self._owned = False


def make_engine(
    name: str, cpus_per_run: float, scratch_dir: Path, address: str, jobs: int | None
) -> LocalEngine | RayEngine:
    if name == "local":
        return LocalEngine(cpus_per_run, scratch_dir, jobs)
    if name == "ray":
        return RayEngine(cpus_per_run, address)
    raise SlamError(f"unknown engine {name!r}; engines: {', '.join(ENGINES)}")

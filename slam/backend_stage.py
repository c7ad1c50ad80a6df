"""The back end as a pipeline stage, in a thread or in a worker process.

GTSAM's Python bindings hold the GIL for the whole of every call, so a back-end update running
in a thread of the front end's process stalls the front end for its duration. With
``backend_process`` (the default) the estimator runs in a worker process: this stage forwards
IMU batches and keyframes over a multiprocessing queue, and a receiver thread publishes the
estimates it sends back (``Latest``), without the front end ever waiting. Sequential mode calls
the estimator directly (deterministic).
"""

from __future__ import annotations

import dataclasses
import logging
import threading
import time
from collections.abc import Callable
from typing import Any

import numpy as np

from slam.backend.config import BackendConfig
from slam.calibration import Calibration
from slam.messages import BackendOutput, EndOfStream, Estimate, ImuBatch, ImuSample, Keyframe
from slam.stage import Latest, Stage, StageError, latency_summary
from slam.worker import READY, WorkerProcess, receive

log = logging.getLogger(__name__)

_NO_IMAGE = np.zeros((0, 0), np.uint8)  # a keyframe sent to the worker carries no images


class _Estimator:
    """Wraps VioBackend: keeps every keyframe's latest pose and reports state changes."""

    def __init__(self, calib: Calibration, cfg: BackendConfig):
        from slam.backend.smoother import VioBackend

        self.backend = VioBackend(calib, cfg)
        self.was_initialized = False
        self.resets_seen = 0

    def add_imu(self, batch: ImuBatch) -> None:
        for sample in batch.samples():
            self.backend.add_imu(sample)

    def add_keyframe(self, kf: Keyframe) -> BackendOutput:
        t0 = time.perf_counter()
        est = self.backend.add_keyframe(kf)
        update_ms = (time.perf_counter() - t0) * 1e3
        events: list[str] = []
        if est is not None and est.initialized and not self.was_initialized:
            self.was_initialized = True
            events.append(f"back end initialised at keyframe {kf.keyframe_id}")
        resets = self.backend.stats.resets
        if resets > self.resets_seen:
            events.append(f"back end reset ({resets} so far)")
            self.resets_seen = resets
        return BackendOutput(est, kf.keyframe_id, update_ms, tuple(events))

    def stats(self) -> dict[str, Any]:
        s = self.backend.stats
        out: dict[str, Any] = {}
        for key, value in vars(s).items():
            if isinstance(value, (int, float, str)):
                out[key] = value
        out["failures"] = list(getattr(s, "failures", []))[:20]
        imu_stats = getattr(self.backend.imu, "stats", None)
        if imu_stats is not None:
            out["imu"] = {k: v for k, v in vars(imu_stats).items() if isinstance(v, (int, float))}
        return out


BACKEND_NICE = 19
"""The back-end worker's nice level. It stays under the normal policy (not SCHED_IDLE like
the other workers) so it still outweighs them 5 to 1 and its estimates stay fresh, yet a
waking front end (nice 0, 68 times its weight) preempts it quickly. Measured on room-aggressive
(``--speed max``, 2 cores, two or four runs each): nice 5 gave FE p99 28-30 ms, nice 10 28-30,
nice 19 25-26; under SCHED_IDLE the FE p99 was 22-25 ms but the back end fell behind the loop
closer (its update p99 170-190 ms) and the online ATE rose from 15-20 mm to 20-30 mm."""


def _worker(calib: Calibration, cfg: BackendConfig, inbox: Any, outbox: Any) -> None:
    """The worker process: feed the estimator, send back outputs, then its final stats."""
    estimator = _Estimator(calib, cfg)
    outbox.put(READY)
    while True:
        msg = receive(inbox)
        if isinstance(msg, EndOfStream):
            break
        if isinstance(msg, ImuBatch):
            estimator.add_imu(msg)
        elif isinstance(msg, Keyframe):
            try:
                outbox.put(estimator.add_keyframe(msg))
            except Exception as exc:  # reported by the stage with its name
                outbox.put(RuntimeError(f"{type(exc).__name__}: {exc}"))
                break
    outbox.put(estimator.stats())


class BackendStage(Stage):
    """Feeds the visual-inertial estimator and publishes its estimates."""

    def __init__(
        self,
        calib: Calibration,
        cfg: BackendConfig,
        latest: Latest,
        on_output: Callable[[BackendOutput], None],
        threaded: bool,
        use_process: bool,
    ):
        super().__init__("backend", maxsize=4000, threaded=threaded)
        self.latest = latest
        self.on_output = on_output
        self.use_process = use_process and threaded
        self.update_ms: list[float] = []
        self.keyframe_poses: dict[int, np.ndarray] = {}
        self.final_stats: dict[str, Any] = {}
        self._pending: list[ImuBatch] = []
        self._pending_samples = 0
        self._lock = threading.Lock()
        if self.use_process:
            self._worker = WorkerProcess(
                "backend",
                _worker,
                (calib, cfg),
                self._on_worker_item,
                self._on_worker_died,
                nice=BACKEND_NICE,
            )
        else:
            self._estimator = _Estimator(calib, cfg)

    def _publish(self, out: BackendOutput) -> None:
        with self._lock:
            self.update_ms.append(out.update_ms)
            est = out.estimate
            if est is not None and est.initialized:
                for kid, pose in est.keyframe_poses.items():
                    self.keyframe_poses[kid] = pose
        if out.estimate is not None:
            self.latest.set(out.estimate)
        self.on_output(out)

    def _on_worker_item(self, item: Any) -> bool:
        if isinstance(item, BackendOutput):
            self._publish(item)
        elif isinstance(item, Exception):
            self._fail(item)  # its final stats follow
        elif isinstance(item, dict):
            self.final_stats = item
            return True
        return False

    def _on_worker_died(self) -> None:
        if self.error is None and not self.final_stats:
            self._fail(RuntimeError("the back-end worker process died"))

    def _fail(self, exc: BaseException) -> None:
        self.error = StageError(self.name, exc, "")
        log.error("%s", self.error)

    def _flush_imu(self) -> None:
        if not self._pending:
            return
        batch = ImuBatch.concatenate(self._pending)
        self._pending = []
        self._pending_samples = 0
        self._worker.put(batch)

    def process(self, msg: Any) -> None:
        if isinstance(msg, ImuSample):
            msg = ImuBatch.from_samples([msg])
        if isinstance(msg, ImuBatch):
            if self.use_process:
                self._pending.append(msg)
                self._pending_samples += len(msg)
                if self._pending_samples >= 50:
                    self._flush_imu()
            else:
                self._estimator.add_imu(msg)
        elif isinstance(msg, Keyframe):
            if self.use_process:
                self._flush_imu()
                # The estimator uses the observations only: not pickling and piping the two
                # images (~720 KB, written in 64 KB pieces that each take the GIL again) keeps
                # that work off the front end's GIL.
                self._worker.put(dataclasses.replace(msg, image_left=_NO_IMAGE, image_right=None))
            else:
                self._publish(self._estimator.add_keyframe(msg))

    def on_end(self) -> None:
        if self.use_process:
            self._flush_imu()
            self._worker.stop(receive_timeout_s=120)
        else:
            self.final_stats = self._estimator.stats()

    def abort(self) -> None:
        super().abort()
        if self.use_process:
            self._worker.terminate()

    def estimate(self) -> Estimate | None:
        value: Estimate | None = self.latest.get()
        return value

    def update_stats(self) -> dict[str, float]:
        with self._lock:
            return latency_summary(list(self.update_ms))

"""The back end as a pipeline stage: keyframes and IMU in, :class:`BackendOutput` out.

GTSAM's Python bindings hold the GIL for the whole of every call, so a back-end update running
in a thread of the front end's process stalls the front end for its duration. With
``backend_process`` (the default) the estimator runs in a worker process
(:class:`slam.runtime.worker.ProcessStage`); each estimate is published to the front end through
a ``Latest`` slot (it never waits) and emitted to the connected stages. Sequential mode calls
the estimator inline (deterministic).
"""

from __future__ import annotations

import dataclasses
import logging
import threading
import time
from collections import deque
from typing import Any

import numpy as np

from slam.backend.config import BackendConfig
from slam.core.calibration import Calibration
from slam.core.latency import latency_summary
from slam.core.messages import (
    BackendFinal,
    BackendFlush,
    BackendOutput,
    Estimate,
    ImuBatch,
    ImuIntrinsics,
    ImuSample,
    Keyframe,
)
from slam.runtime.stage import Latest
from slam.runtime.worker import ProcessStage, WorkerCore

log = logging.getLogger(__name__)

_NO_IMAGE = np.zeros((0, 0), np.uint8)  # a keyframe sent to the worker carries no images


class _Estimator(WorkerCore):
    """Wraps VioBackend: reports each keyframe's update and the estimator's state changes."""

    def __init__(self, calib: Calibration, cfg: BackendConfig, publish_inertial: bool = False):
        from slam.backend.smoother import VioBackend

        self.backend = VioBackend(calib, cfg, publish_inertial)
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
        attempts = self.backend.stats.mono_init_attempts
        if attempts and attempts[-1]["t_ns"] == kf.t_ns:
            a = attempts[-1]
            verdict = "accepted" if a["accepted"] else f"rejected: {a['reason']}"
            events.append(f"monocular alignment: scale {a['scale']:.3f} m per VO unit, {verdict}")
        checks = self.backend.stats.mono_scale_checks
        if checks and checks[-1]["t_ns"] == kf.t_ns and checks[-1].get("corrected"):
            events.append(f"monocular scale check: {checks[-1]['scale']:.3f}, smoother corrected")
        if checks and checks[-1]["t_ns"] == kf.t_ns and checks[-1].get("reinit"):
            residual_mm = checks[-1]["residual_m"] * 1e3
            events.append(f"monocular scale check: residual {residual_mm:.1f} mm, start redone")
        resets = self.backend.stats.resets
        if resets > self.resets_seen:
            events.append(f"back end reset ({resets} so far)")
            self.resets_seen = resets
        return BackendOutput(
            est,
            kf.keyframe_id,
            update_ms,
            tuple(events),
            self.backend.last_scale,
            self.backend.take_inertial(),
        )

    def handle(self, msg: Any) -> list[Any]:
        if isinstance(msg, ImuBatch):
            self.add_imu(msg)
            return []
        if isinstance(msg, Keyframe):
            return [self.add_keyframe(msg)]
        if isinstance(msg, BackendFlush):
            est = self.backend.flush_held()
            out = [] if est is None else [BackendOutput(est, est.keyframe_id, 0.0)]
            inertial = self.backend.take_inertial(window=True)
            if inertial:  # the window's states, final now
                out.append(BackendOutput(None, -1, 0.0, inertial=inertial))
            return out
        return []

    def finish(self, interrupted: bool) -> BackendFinal:
        return BackendFinal(self.stats())

    def stats(self) -> dict[str, Any]:
        s = self.backend.stats
        out: dict[str, Any] = {}
        for key, value in vars(s).items():
            if isinstance(value, (int, float, str)):
                out[key] = value
        out["failures"] = list(getattr(s, "failures", []))[:20]
        if s.mono_init_attempts:
            out["mono_init_attempts"] = list(s.mono_init_attempts)
        if s.mono_scale_checks:
            out["mono_scale_checks"] = list(s.mono_scale_checks)
        if self.backend.time_offset is not None:
            out["time_offset"] = self.backend.time_offset.summary()
        if self.backend.intrinsics is not None:
            out["imu_intrinsics"] = self.backend.intrinsics.summary()
        imu_stats = getattr(self.backend.imu, "stats", None)
        if imu_stats is not None:
            out["imu"] = {k: v for k, v in vars(imu_stats).items() if isinstance(v, (int, float))}
        return out


def _make_core(calib: Calibration, cfg: BackendConfig, publish_inertial: bool) -> _Estimator:
    return _Estimator(calib, cfg, publish_inertial)


class BackendStage(ProcessStage):
    """Feeds the visual-inertial estimator, publishes its estimates and emits its outputs."""

    def __init__(
        self,
        calib: Calibration,
        cfg: BackendConfig,
        latest: Latest,
        threaded: bool,
        use_process: bool,
        publish_inertial: bool = False,
        estimate_delay_ns: int = 0,
    ):
        """``publish_inertial``: the outputs carry the back end's final keyframe states and
        their IMU readings (``BackendOutput.inertial``: ``loop.global_ba_imu``).
        ``estimate_delay_ns`` (sequential runs: ``player.sequential_estimate_delay_ms``): each
        estimate reaches ``latest`` (the front end) only once the IMU stream has passed its
        keyframe's stamp by this much sensor time, as a loaded machine's back end would
        deliver it; the emitted outputs are not delayed. 0: at once."""
        super().__init__(
            "backend",
            4000,
            threaded,
            _make_core,
            (calib, cfg, publish_inertial),
            role="backend",
            in_process=use_process,
        )
        self.latest = latest
        self.update_ms: list[float] = []
        self.keyframe_poses: dict[int, np.ndarray] = {}
        # (t_ns, gyro bias rad/s, accel bias m/s^2) of every initialised estimate, in order
        self.biases: list[tuple[int, np.ndarray, np.ndarray]] = []
        self.final_stats: dict[str, Any] = {}
        self._pending: list[ImuBatch] = []
        self._pending_samples = 0
        self._lock = threading.Lock()
        if estimate_delay_ns and threaded:
            raise ValueError("a delayed estimate is for sequential runs only")
        self.estimate_delay_ns = estimate_delay_ns
        self._held: deque[Estimate] = deque()  # estimates not yet due (estimate_delay_ns)
        self.keyframe_waits_for_imu = cfg.keyframe_waits_for_imu
        self._waiting: Keyframe | None = None  # waiting for the IMU reading after its stamp
        self._imu_newest_ns: int | None = None  # the newest IMU reading handed on
        self.keyframes_waited_for_imu = 0
        self.keyframes_not_covered_by_imu = 0

    def on_output(self, item: Any) -> None:
        if not isinstance(item, BackendOutput):
            return
        with self._lock:
            if item.estimate is not None or item.keyframe_id >= 0:  # not the end's states alone
                self.update_ms.append(item.update_ms)
            est = item.estimate
            if est is not None and est.initialized:
                for kid, pose in est.keyframe_poses.items():
                    self.keyframe_poses[kid] = pose
                self.biases.append((est.t_ns, est.bias_gyro_rad_s, est.bias_accel_m_s2))
        if item.estimate is not None:
            if self.estimate_delay_ns > 0:
                self._held.append(item.estimate)
            else:
                self.latest.set(item.estimate)
        self.emit(item)

    def _release_held(self, now_ns: int | None) -> None:
        """Publish the held estimates due at sensor time ``now_ns`` (None: all), in order."""
        held = self._held
        while held and (now_ns is None or held[0].t_ns + self.estimate_delay_ns <= now_ns):
            self.latest.set(held.popleft())

    def biases_at(self, t_ns: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The gyro (rad/s) and accelerometer (m/s^2) biases of the first initialised estimate
        at or after each time (the last one after the last), (N, 3) each; zeros without any."""
        with self._lock:
            history = list(self.biases)
        t_ns = np.asarray(t_ns, dtype=np.int64)
        if not history:
            return np.zeros((len(t_ns), 3)), np.zeros((len(t_ns), 3))
        times = np.array([h[0] for h in history], dtype=np.int64)
        pick = np.minimum(np.searchsorted(times, t_ns, side="left"), len(history) - 1)
        gyro = np.array([h[1] for h in history], dtype=float).reshape(-1, 3)
        accel = np.array([h[2] for h in history], dtype=float).reshape(-1, 3)
        return gyro[pick], accel[pick]

    def on_final(self, payload: Any) -> None:
        if isinstance(payload, BackendFinal):
            self.final_stats = payload.stats

    def _flush_imu(self) -> None:
        if not self._pending:
            return
        batch = ImuBatch.concatenate(self._pending)
        self._pending = []
        self._pending_samples = 0
        self.send(batch)

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
                self.send(msg)
            if len(msg):
                self._imu_newest_ns = int(msg.t_ns[-1])
            if self._waiting is not None and self._covered(self._waiting):
                self._send_keyframe(self._waiting)
                self._waiting = None
            if self._held and len(msg):
                self._release_held(int(msg.t_ns[-1]))
        elif isinstance(msg, Keyframe):
            if not self.keyframe_waits_for_imu:
                self._send_keyframe(msg)
                return
            if self._waiting is not None:  # a keyframe waits at most until the next one
                self.keyframes_not_covered_by_imu += 1
                self._send_keyframe(self._waiting)
                self._waiting = None
            if self._covered(msg):
                self._send_keyframe(msg)
            else:
                self.keyframes_waited_for_imu += 1
                self._waiting = msg

    def _covered(self, kf: Keyframe) -> bool:
        """Whether an IMU reading at or after the keyframe's stamp has been handed on."""
        return self._imu_newest_ns is not None and self._imu_newest_ns >= kf.t_ns

    def _send_keyframe(self, kf: Keyframe) -> None:
        if self.use_process:
            self._flush_imu()
            # The estimator uses the observations only: not pickling and piping the two
            # images (~720 KB, written in 64 KB pieces that each take the GIL again) keeps
            # that work off the front end's GIL.
            self.send(dataclasses.replace(kf, image_left=_NO_IMAGE, image_right=None))
        else:
            self.send(kf)

    def on_end(self) -> None:
        if self._waiting is not None and not self.interrupted:  # no reading came after it
            self.keyframes_not_covered_by_imu += 1
            self._send_keyframe(self._waiting)
        self._waiting = None
        if self.use_process and not self.interrupted:
            self._flush_imu()
        self.send(BackendFlush())  # keyframes held for the time offset
        self._release_held(None)  # the run is over: the front end's finish() sees the last
        self.end_worker()

    def estimate(self) -> Estimate | None:
        value: Estimate | None = self.latest.get()
        return value

    def imu_intrinsics(self) -> ImuIntrinsics | None:
        """The IMU correction matrices of the latest estimate (None: none applied)."""
        est = self.latest.get()
        return None if est is None else est.imu_intrinsics

    def time_offset_ns(self) -> int:
        """The camera-IMU offset to stamp frames with now (0 until the back end knows it)."""
        est = self.latest.get()
        if est is None or est.time_offset is None:
            return 0
        return int(est.time_offset.applied_ns)

    def update_stats(self) -> dict[str, float]:
        with self._lock:
            return latency_summary(list(self.update_ms))

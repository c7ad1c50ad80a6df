"""Loop closure entirely in a worker process, with a mirror of its keyframe store here.

Measured: with the loop closer in a thread of the front end's process, its Python/numpy work
(describing keyframes, BoW, the database, verification, building and applying pose graphs)
raised the front end's p99 latency from ~22 ms to ~32 ms on 2 cores (the GIL), while its OpenCV
ORB detection alone did not. So in concurrent mode everything runs in a spawned worker process
(which also optimises the pose graph inline). Each keyframe's :class:`KeyframeDescription` comes
back and is added to a local :class:`KeyframeStore`, so the front end's :class:`Relocaliser`
still answers synchronously, in its own thread, when tracking is lost.
"""

from __future__ import annotations

import dataclasses
import logging
import threading
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from slam.calibration import Calibration
from slam.loop.config import LoopClosureConfig
from slam.loop.relocaliser import Relocaliser
from slam.loop.stage import OdometryRefresher, before_first_smoothed
from slam.loop.store import KeyframeDescription, KeyframeStore
from slam.loop.vocabulary import load_default_vocabulary
from slam.messages import EndOfStream, Keyframe, LoopCorrection
from slam.stage import Latest, Stage, StageError
from slam.worker import READY, WorkerProcess, receive

LOOP_WORKER_NICE = 10

log = logging.getLogger(__name__)


@dataclass(frozen=True, eq=False)
class _LoopInput:
    keyframe: Keyframe  # without the right image (not needed here)
    world_from_body_odom: np.ndarray
    refreshed: dict[int, np.ndarray]  # newer odometry of recent keyframes


@dataclass(frozen=True, eq=False)
class _Unsmoothed:
    """Keyframes from before the back end's initialisation (sent at the end, before the
    global adjustment)."""

    keyframe_ids: frozenset[int]


@dataclass(frozen=True, eq=False)
class _LoopOutput:
    description: KeyframeDescription
    world_from_body_odom: np.ndarray
    status: str  # "", or the loop event's status
    reason: str
    correction: LoopCorrection | None


@dataclass(frozen=True, eq=False)
class _LoopFinal:
    stats: dict[str, Any]
    keyframe_map_from_odom: dict[int, np.ndarray]
    corrected_poses: dict[int, np.ndarray]


def _worker(calib: Calibration, cfg: LoopClosureConfig, inbox: Any, outbox: Any) -> None:
    from slam.loop.closer import LoopCloser

    closer = LoopCloser(calib, cfg, None, inline_pgo=True)
    outbox.put(READY)
    while True:
        msg = receive(inbox)
        if isinstance(msg, EndOfStream):
            break
        if isinstance(msg, _Unsmoothed):
            closer.exclude_from_adjustment = set(msg.keyframe_ids)
            continue
        try:
            for kid, pose in msg.refreshed.items():
                if kid in closer.odom:
                    closer.update_odometry(kid, pose)
            event = closer.add_keyframe(msg.keyframe, msg.world_from_body_odom)
            kid = msg.keyframe.keyframe_id
            # The mirror only serves relocalisation, which matches a new image against stored
            # landmark descriptors: the keyframe's own whole-image ORB set stays here (it
            # would double the mirror's memory).
            desc = closer.store.description(kid)
            mirror = dataclasses.replace(
                desc,
                query_xy_undist=np.zeros((0, 2), desc.query_xy_undist.dtype),
                query_desc=np.zeros((0, desc.query_desc.shape[1]), desc.query_desc.dtype),
            )
            outbox.put(
                _LoopOutput(
                    mirror,
                    msg.world_from_body_odom,
                    "" if event is None else event.status,
                    "" if event is None else event.reason,
                    None if event is None else event.correction,
                )
            )
        except Exception as exc:  # reported by the stage with its name
            outbox.put(RuntimeError(f"{type(exc).__name__}: {exc}"))
            return
    ba = closer.global_adjustment()
    summary = dict(closer.stats.summary())
    summary["mode"] = "worker process"
    summary["global_ba"] = None if ba is None else ba.summary()
    summary["loops"] = [
        {
            "loop_id": r.loop_id,
            "query_kf": r.query_kf_id,
            "match_kf": r.match_kf_id,
            "query_t_ns": closer.t_ns_of.get(r.query_kf_id),
            "match_t_ns": closer.t_ns_of.get(r.match_kf_id),
            "inliers": r.inliers,
            "active": r.active,
        }
        for r in closer.loops
    ]
    if cfg.debug_graph:
        summary["graph"] = closer.graph_dump()
    outbox.put(_LoopFinal(summary, closer.keyframe_map_from_odom(), closer.corrected_poses()))


class LoopClosureWorkerStage(Stage):
    """Keyframes in, :class:`LoopCorrection` out; the closer runs in a worker process."""

    def __init__(
        self,
        calib: Calibration,
        cfg: LoopClosureConfig,
        odometry_pose: Callable[[int], np.ndarray | None],
        on_correction: Callable[[LoopCorrection], None],
        idle_worker: bool = False,
        smoothed: Callable[[int], bool] | None = None,
    ):
        """``idle_worker``: run the worker process under SCHED_IDLE (:func:`lower_priority`).
        ``smoothed(keyframe id)``: whether the back end has estimated that keyframe (asked at
        the end; the others stay out of the global adjustment)."""
        super().__init__("loop", maxsize=256, threaded=True)
        self.cfg = cfg
        self.smoothed = smoothed
        self.odometry_pose = odometry_pose
        self.refresher = OdometryRefresher(odometry_pose)
        self.on_correction = on_correction
        self.latest = Latest()
        self.store = KeyframeStore()
        self.relocaliser = Relocaliser(calib, self.store, cfg, load_default_vocabulary())
        self._lock = threading.RLock()
        self.t_ns_of: dict[int, int] = {}
        self.segment_of: dict[int, int] = {}
        self._final: _LoopFinal | None = None
        self._events: list[tuple[str, str]] = []
        self._worker = WorkerProcess(
            "loop",
            _worker,
            (calib, cfg),
            self._on_worker_item,
            self._on_worker_died,
            nice=LOOP_WORKER_NICE,  # background work: the front end and back end come first
            idle=idle_worker,
        )

    # -- stage ---------------------------------------------------------------------------
    def process(self, msg: Any) -> None:
        if not isinstance(msg, Keyframe):
            return
        refreshed = self.refresher.refreshed()
        odom = self.refresher.new_keyframe(msg.keyframe_id, msg.world_from_body_vo)
        with self.store.lock:  # the relocaliser answers in the keyframe's current odometry
            for kid, pose in refreshed.items():
                if self.store.has(kid):
                    self.store.set_odometry(kid, pose)
        with self._lock:
            self.t_ns_of[msg.keyframe_id] = msg.t_ns
            self.segment_of[msg.keyframe_id] = msg.segment_id
        self._worker.put(_LoopInput(dataclasses.replace(msg, image_right=None), odom, refreshed))

    def _on_worker_item(self, item: Any) -> bool:
        if isinstance(item, _LoopOutput):
            d = item.description
            with self.store.lock:  # the relocaliser reads under the same lock
                latest = self.refresher.sent.get(d.kf_id, item.world_from_body_odom)
                self.store.add_description(d, latest)
                self.store.database.add(d.kf_id, d.t_ns, d.bow)
            if item.status:
                self._events.append((item.status, item.reason))
            if item.correction is not None:
                self.store.set_corrected(item.correction.corrected_keyframe_poses)
                self.latest.set(item.correction)
                self.on_correction(item.correction)
            return False
        if isinstance(item, _LoopFinal):
            self._final = item
        elif isinstance(item, Exception):
            self.error = StageError(self.name, item, "")
            log.error("%s", self.error)
        return True

    def _on_worker_died(self) -> None:
        if self._final is None and self.error is None:
            self.error = StageError(self.name, RuntimeError("the loop-closure worker died"), "")

    def on_end(self) -> None:
        if self.smoothed is not None:
            with self._lock:
                kids = list(self.t_ns_of)
            self._worker.put(_Unsmoothed(frozenset(before_first_smoothed(kids, self.smoothed))))
        self._worker.stop(receive_timeout_s=600)

    def abort(self) -> None:
        super().abort()
        self._worker.terminate()

    # -- outputs (complete once the stage has ended) ----------------------------------------
    def keyframe_corrections(self) -> dict[int, np.ndarray]:
        """Per keyframe id: corrected pose @ inverse(odometry pose), from the worker's end."""
        return {} if self._final is None else dict(self._final.keyframe_map_from_odom)

    def corrected_keyframe_poses(self) -> dict[int, np.ndarray]:
        return {} if self._final is None else dict(self._final.corrected_poses)

    def keyframe_times_and_segments(self) -> tuple[dict[int, int], dict[int, int]]:
        with self._lock:
            return dict(self.t_ns_of), dict(self.segment_of)

    def stats(self) -> dict[str, Any]:
        out: dict[str, Any] = {} if self._final is None else dict(self._final.stats)
        out["relocalisation"] = self.relocaliser.stats()
        out["invalid_odometry_poses"] = self.refresher.invalid_poses
        out["odometry_frame_jumps"] = self.refresher.frame_jumps
        return out

"""Loop closure as a pipeline stage: keyframes in, :class:`LoopCorrection` out.

Measured: with the loop closer in a thread of the front end's process, its Python/numpy work
(describing keyframes, BoW, the database, verification, building and applying pose graphs)
raised the front end's p99 latency from ~22 ms to ~32 ms on 2 cores (the GIL), while its OpenCV
ORB detection alone did not. So in concurrent runs the :class:`LoopCore` (the closer, with its
pose-graph optimisation inline) runs in a worker process, and inline in sequential runs. Each
keyframe's :class:`KeyframeDescription` comes back and is added to a mirror
:class:`KeyframeStore` here, so the front end's :class:`Relocaliser` answers synchronously, in
its own thread, when tracking is lost.

Odometry poses come as messages: the back end's estimates (:class:`BackendOutput`) and, for
keyframes it has not estimated, the front end's belief, followed through its
:class:`FrontendCorrection` messages. The last few keyframes' poses are resent before each new
one (:class:`slam.loop.odometry.OdometryRefresher`), since the back end keeps refining its
window.
"""

from __future__ import annotations

import dataclasses
import logging
import threading
import time
from typing import TYPE_CHECKING, Any

import numpy as np

from slam.core.calibration import Calibration
from slam.core.geometry import invert_transform
from slam.core.messages import (
    BackendOutput,
    FrontendCorrection,
    Keyframe,
    KeyframeInertial,
    LoopEnd,
    LoopFinal,
    LoopInput,
    LoopOutput,
)
from slam.frontend.tracker import MAX_STORED_KEYFRAME_POSES
from slam.loop.config import LoopClosureConfig
from slam.loop.odometry import OdometryRefresher, before_first_smoothed
from slam.loop.relocaliser import Relocaliser
from slam.loop.store import KeyframeStore
from slam.loop.vocabulary import load_default_vocabulary
from slam.runtime.stage import Latest
from slam.runtime.worker import ProcessStage, WorkerCore

if TYPE_CHECKING:
    from slam.loop.global_ba import GlobalBaResult

log = logging.getLogger(__name__)


class LoopCore(WorkerCore):
    """The loop closer behind the stage (in its worker process, or inline)."""

    def __init__(self, calib: Calibration, cfg: LoopClosureConfig):
        from slam.loop.closer import LoopCloser

        self.cfg = cfg
        self.closer = LoopCloser(calib, cfg, None, inline_pgo=True)

    def handle(self, msg: Any) -> list[Any]:
        closer = self.closer
        if isinstance(msg, LoopEnd):
            for kid, pose in msg.refreshed.items():
                if kid in closer.odom:
                    closer.update_odometry(kid, pose)
            closer.exclude_from_adjustment = set(msg.unsmoothed_ids)
            closer.inertial = dict(msg.inertial)
            return []
        if not isinstance(msg, LoopInput):
            return []
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
        return [
            LoopOutput(
                mirror,
                msg.world_from_body_odom,
                "" if event is None else event.status,
                "" if event is None else event.reason,
                None if event is None else event.correction,
            )
        ]

    def finish(self, interrupted: bool) -> LoopFinal:
        """The global adjustment (skipped when the run was interrupted or the end of the run
        has already taken most of its time budget; else given what is left of it), then the
        state. In a worker process the state without the adjustment goes first, as a fallback
        the stage ends with if the adjustment overruns its budget by ``global_ba_grace_s``
        (its graph and first iteration cannot be cut)."""
        closer = self.closer
        spent_s = 0.0 if self.end_began_s is None else time.perf_counter() - self.end_began_s
        budget_s = closer.global_adjustment_budget_s()
        skipped = None
        if interrupted:
            skipped = "run interrupted"
        elif (
            budget_s is not None
            and budget_s - spent_s < closer.cfg.global_ba_min_budget_share * budget_s
        ):
            # The backlog (a worker behind on a busy machine) used most of the budget: the
            # adjustment's first iteration alone would overrun it by seconds there.
            skipped = f"the loop backlog used its time budget ({spent_s:.1f} of {budget_s:.1f} s)"
        if skipped is None and budget_s is not None and self.offer_fallback is not None:
            began_s = time.perf_counter() if self.end_began_s is None else self.end_began_s
            self.offer_fallback(
                self._final(None, f"stopped: not done within its time budget ({budget_s:.1f} s)"),
                began_s + budget_s + closer.cfg.global_ba_grace_s,
            )
        ba = None if skipped else closer.global_adjustment(spent_s)
        return self._final(ba, skipped)

    def _final(self, ba: GlobalBaResult | None, skipped: str | None) -> LoopFinal:
        closer = self.closer
        summary = dict(closer.stats.summary())
        summary["global_ba"] = None if ba is None else ba.summary()
        summary["global_ba_skipped"] = skipped
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
        if self.cfg.debug_graph:
            summary["graph"] = closer.graph_dump()
        return LoopFinal(summary, closer.keyframe_map_from_odom(), closer.corrected_poses())


class _OdometrySource:
    """Each keyframe's odometry pose as the messages so far tell it: the back end's estimate,
    else the front end's belief (its pose at creation, moved by every later front-end
    correction; like the front end, only its newest ``MAX_STORED_KEYFRAME_POSES``).

    A keyframe from before the back end's initialisation is never estimated by it: it keeps
    its visual-odometry pose relative to the first keyframe the back end estimated, and follows
    that one's estimate. Measured on room-figure8: as the front end's belief, keyframes 0 and 1
    stayed where the back end's first estimate of keyframe 2 put them, 15 mm from where its
    smoothed estimate went, and the first loop (to keyframe 0) corrected the live pose by that
    error (a 2.3 cm jump the wrong way)."""

    def __init__(self) -> None:
        self.backend: dict[int, np.ndarray] = {}
        self._vo: dict[int, tuple[np.ndarray, np.ndarray]] = {}  # kid -> (pose, chain at birth)
        self._chain = np.eye(4)  # product of the front end's corrections so far
        self._first_smoothed: int | None = None

    def add_keyframe(self, kf: Keyframe) -> None:
        self._vo[kf.keyframe_id] = (np.asarray(kf.world_from_body_vo, float), self._chain)
        if len(self._vo) > MAX_STORED_KEYFRAME_POSES:
            del self._vo[min(self._vo)]

    def frontend_correction(self, msg: FrontendCorrection) -> None:
        self._chain = msg.new_from_old @ self._chain

    def backend_output(self, out: BackendOutput) -> None:
        est = out.estimate
        if est is not None and est.initialized and est.keyframe_poses:
            self.backend.update(est.keyframe_poses)
            first = min(est.keyframe_poses)
            if self._first_smoothed is None or first < self._first_smoothed:
                self._first_smoothed = first

    def _belief(self, kid: int) -> np.ndarray | None:
        vo = self._vo.get(kid)
        if vo is None:
            return None
        pose, chain_at_birth = vo
        if chain_at_birth is self._chain:
            return pose
        return self._chain @ invert_transform(chain_at_birth) @ pose

    def __call__(self, kid: int) -> np.ndarray | None:
        pose = self.backend.get(kid)
        if pose is not None:
            return pose
        belief = self._belief(kid)
        first = self._first_smoothed
        if belief is None or first is None or kid > first:
            return belief
        first_belief = self._belief(first)
        if first_belief is None:
            return belief
        return self.backend[first] @ invert_transform(first_belief) @ belief

    def smoothed(self, kid: int) -> bool:
        return kid in self.backend


class LoopClosureStage(ProcessStage):
    """Keyframes, back-end outputs and front-end corrections in; :class:`LoopCorrection` out
    (emitted, and in :attr:`latest`)."""

    end_timeout_s = 600.0  # the global adjustment at the end: 5-30 s on the suite

    def __init__(
        self,
        calib: Calibration,
        cfg: LoopClosureConfig,
        threaded: bool,
        idle_worker: bool = False,
    ):
        """``idle_worker``: run the worker process under SCHED_IDLE (``slam.runtime.priority``).
        A sequential run (not ``threaded``) is deterministic, so its global adjustment gets no
        wall-clock budget."""
        if not threaded:
            cfg = dataclasses.replace(cfg, global_ba_budget_fraction=0.0)
        super().__init__(
            "loop",
            256,
            threaded,
            LoopCore,
            (calib, cfg),
            role="loop",
            idle=idle_worker,
        )
        self.cfg = cfg
        self.odometry = _OdometrySource()
        self.refresher = OdometryRefresher(self.odometry)
        self.latest = Latest()
        self.store = KeyframeStore()
        self.relocaliser = Relocaliser(calib, self.store, cfg, load_default_vocabulary())
        self._lock = threading.RLock()
        self.t_ns_of: dict[int, int] = {}
        self.segment_of: dict[int, int] = {}
        self._final: LoopFinal | None = None
        self._events: list[tuple[str, str, int, int]] = []
        # keyframe id -> the back end's final inertial state (``global_ba_imu``)
        self.inertial: dict[int, KeyframeInertial] = {}

    # -- stage ---------------------------------------------------------------------------
    def process(self, msg: Any) -> None:
        if isinstance(msg, BackendOutput):
            self.odometry.backend_output(msg)
            for state in msg.inertial:
                self.inertial[state.keyframe_id] = state
            return
        if isinstance(msg, FrontendCorrection):
            self.odometry.frontend_correction(msg)
            return
        if not isinstance(msg, Keyframe) or not msg.metric:
            return  # a monocular keyframe before the scale is known is not for the map
        self.odometry.add_keyframe(msg)
        refreshed = self.refresher.refreshed()
        odom = self.refresher.new_keyframe(msg.keyframe_id, msg.world_from_body_vo)
        with self.store.lock:  # the relocaliser answers in the keyframe's current odometry
            for kid, pose in refreshed.items():
                if self.store.has(kid):
                    self.store.set_odometry(kid, pose)
        with self._lock:
            self.t_ns_of[msg.keyframe_id] = msg.t_ns
            self.segment_of[msg.keyframe_id] = msg.segment_id
        self.send(LoopInput(dataclasses.replace(msg, image_right=None), odom, refreshed))

    def on_output(self, item: Any) -> None:
        if not isinstance(item, LoopOutput):
            return
        d = item.description
        with self.store.lock:  # the relocaliser reads under the same lock
            latest = self.refresher.sent.get(d.kf_id, item.world_from_body_odom)
            self.store.add_description(d, latest)
            self.store.database.add(d.kf_id, d.t_ns, d.bow)
        if item.status:
            match = -1 if item.correction is None else item.correction.match_keyframe_id
            self._events.append((item.status, item.reason, d.kf_id, match))
            log.info("loop %s: keyframe %d %s", item.status, d.kf_id, item.reason)
        if item.correction is not None:
            self.store.set_corrected(item.correction.corrected_keyframe_poses)
            self.latest.set(item.correction)
            self.emit(item.correction)

    def on_final(self, payload: Any) -> None:
        if isinstance(payload, LoopFinal):
            self._final = payload

    def on_end(self) -> None:
        if not self.interrupted:
            with self._lock:
                kids = list(self.t_ns_of)
            unsmoothed = before_first_smoothed(kids, self.odometry.smoothed)
            # The back end's last estimates (and the front end's change of frame, when the
            # back end initialised after the last frame) arrived after the last keyframe.
            self.send(
                LoopEnd(
                    frozenset(unsmoothed), self.refresher.refreshed(full=True), dict(self.inertial)
                )
            )
        self.end_worker()

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
        out["mode"] = "process" if self.use_process else "inline"
        out["rejections"] = [
            {"query_kf": q, "reason": r} for status, r, q, _ in self._events if status == "rejected"
        ][:50]
        out["relocalisation"] = self.relocaliser.stats()
        out["invalid_odometry_poses"] = self.refresher.invalid_poses
        out["odometry_frame_jumps"] = self.refresher.frame_jumps
        return out

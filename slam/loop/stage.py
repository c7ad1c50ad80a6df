"""The loop closer as a pipeline stage; pose-graph optimisation in a worker process.

Consumes :class:`Keyframe` messages (after the back end, or beside it). Odometry poses come from
a callable (``kf_id -> world_from_body or None``: back-end-optimised poses when available, else
the keyframe's own ``world_from_body_vo``); the last few keyframes' poses are refreshed before
each new one, since the back end keeps refining its window.

GTSAM holds the GIL for a whole ``optimize()``, so in concurrent mode each pose-graph
optimisation runs in a spawned worker process (one at a time; a loop accepted meanwhile is
optimised right after). The result is applied under a lock from the executor's callback thread
and published through ``on_correction`` and :attr:`latest`. Sequential mode optimises inline
(deterministic).
"""

from __future__ import annotations

import logging
import multiprocessing as mp
import threading
import time
from collections.abc import Callable
from concurrent.futures import Future, ProcessPoolExecutor
from typing import Any

import numpy as np

from slam.calibration import Calibration
from slam.geometry import invert_transform, is_rigid, rotation_angle_rad
from slam.loop.closer import LoopCloser, LoopEvent, PgoOutcome, run_pgo
from slam.loop.config import LoopClosureConfig
from slam.loop.relocaliser import Relocaliser
from slam.loop.vocabulary import Vocabulary
from slam.messages import Keyframe, LoopCorrection
from slam.stage import Latest, Stage, StageError

log = logging.getLogger(__name__)

REFRESH_LAST_KEYFRAMES = 30  # odometry poses re-read per new keyframe (the back end's window)
FULL_REFRESH_EVERY = 10  # ... and the older ones', every this many keyframes (see below)
FRAME_JUMP_M = 0.1  # an old keyframe moving more than this between sweeps: a change of frame
FRAME_JUMP_DEG = 3.0
RIGID_TOL = 1e-6  # max |R^T R - I| of an odometry pose the closer accepts


class OdometryRefresher:
    """Which keyframes' odometry poses changed since they were last handed to the closer.

    Every keyframe, the last ``REFRESH_LAST_KEYFRAMES`` are re-read (the back end's window keeps
    refining them). Every ``FULL_REFRESH_EVERY`` keyframes, the older ones are re-read too, but
    resent only when they *jumped* since the previous sweep by more than a change of frame
    threshold (``FRAME_JUMP_M`` / ``FRAME_JUMP_DEG``). Why both rules, measured:

    * at ``--speed max`` on the hall, the back end's first (gravity-aligning) estimate arrived
      ~40 keyframes late, after the first 10 keyframes had left the recent window: they stayed
      in the pre-initialisation VO frame (a 94 deg wrong odometry edge; loops to the start
      rejected by the robust kernel). The sweep catches such a change of frame;
    * keyframes without a back-end pose (before initialisation) come from the front end's
      belief, which every estimate re-anchors by the current drift correction: resending all
      their small changes dragged keyframe 1 of room-aggressive 115 mm / 2.2 deg away from
      keyframe 2 (corrupting every loop to it). Small changes of old keyframes are ignored.
    """

    def __init__(self, odometry_pose: Callable[[int], np.ndarray | None]):
        self._source = odometry_pose
        self.sent: dict[int, np.ndarray] = {}
        self._seen: dict[int, np.ndarray] = {}  # old keyframes' source poses at the last sweep
        self._order: list[int] = []
        self.invalid_poses = 0
        self.frame_jumps = 0

    def odometry_pose(self, kid: int) -> np.ndarray | None:
        """The source's pose when it is a rigid transform, else None (counted): measured, a
        diverging back end once published a keyframe pose with a 'rotation' of norm ~12."""
        pose = self._source(kid)
        if pose is None:
            return None
        pose = np.asarray(pose, dtype=float)
        if not is_rigid(pose, tol=RIGID_TOL):
            self.invalid_poses += 1
            return None
        return pose

    def refreshed(self) -> dict[int, np.ndarray]:
        """Changed poses to resend before the next keyframe (also recorded as sent)."""
        out: dict[int, np.ndarray] = {}
        recent = self._order[-REFRESH_LAST_KEYFRAMES:]
        for kid in recent:
            pose = self.odometry_pose(kid)
            if pose is None:
                continue
            self._seen[kid] = pose
            old = self.sent.get(kid)
            if old is None or not np.array_equal(old, pose):
                out[kid] = self.sent[kid] = np.array(pose, dtype=float)
        if len(self._order) % FULL_REFRESH_EVERY == 0:
            # Vectorised over the old keyframes: this runs in the main process, and a Python
            # loop over hundreds of poses held the GIL for milliseconds at a time.
            old_ids = self._order[: max(len(self._order) - len(recent), 0)]
            found = [(kid, p) for kid in old_ids if (p := self._source(kid)) is not None]
            if not found:
                return out
            ids = [kid for kid, _ in found]
            poses = np.array([p for _, p in found], dtype=float).reshape(-1, 4, 4)
            before_all = np.array([self._seen.get(k, self.sent[k]) for k in ids]).reshape(-1, 4, 4)
            valid = is_rigid(poses, tol=RIGID_TOL)
            self.invalid_poses += int((~valid).sum())
            changed = valid & ~(poses == before_all).all(axis=(1, 2))  # usually: frozen poses
            for i in np.flatnonzero(changed).tolist():
                kid, pose, before = ids[i], poses[i], before_all[i]
                self._seen[kid] = pose.copy()
                jump = invert_transform(before) @ pose
                angle_deg = float(np.degrees(rotation_angle_rad(jump[:3, :3])))
                if np.linalg.norm(jump[:3, 3]) > FRAME_JUMP_M or angle_deg > FRAME_JUMP_DEG:
                    out[kid] = self.sent[kid] = np.array(pose, dtype=float)
                    self.frame_jumps += 1
        return out

    def new_keyframe(self, kid: int, fallback: np.ndarray) -> np.ndarray:
        """The odometry pose to send with a new keyframe (``fallback`` when none is known)."""
        pose = self.odometry_pose(kid)
        odom = np.array(fallback if pose is None else pose, dtype=float)
        self.sent[kid] = odom
        self._order.append(kid)
        return odom


def before_first_smoothed(kf_ids: list[int], smoothed: Callable[[int], bool]) -> set[int]:
    """The keyframes before the first one the back end estimated (its initialisation). Only
    those: at the end of a run, the back end may still be busy with the newest keyframes."""
    first = min((k for k in kf_ids if smoothed(k)), default=None)
    return set() if first is None else {k for k in kf_ids if k < first}


def _warm_up() -> bool:
    """Import GTSAM in the worker before the first loop needs it, at a lower priority than
    the front end (pose-graph optimisation only has to finish soon, not within a frame)."""
    from slam.worker import lower_priority

    lower_priority(5)
    import slam.posegraph  # noqa: F401

    return True


class LoopClosureStage(Stage):
    """Keyframes in, :class:`LoopCorrection` out (``on_correction`` and ``latest``)."""

    def __init__(
        self,
        calib: Calibration,
        cfg: LoopClosureConfig,
        odometry_pose: Callable[[int], np.ndarray | None],
        on_correction: Callable[[LoopCorrection], None],
        threaded: bool,
        vocabulary: Vocabulary | None = None,
        queue_size: int = 64,
        smoothed: Callable[[int], bool] | None = None,
    ):
        """``smoothed(keyframe id)``: whether the back end has estimated that keyframe (asked
        at the end; the others stay out of the global adjustment)."""
        super().__init__("loop", maxsize=queue_size, threaded=threaded)
        self.cfg = cfg
        self.smoothed = smoothed
        self.closer = LoopCloser(calib, cfg, vocabulary, inline_pgo=False)
        self.relocaliser = Relocaliser(calib, self.closer.store, cfg, self.closer.vocab)
        self.odometry_pose = odometry_pose
        self.refresher = OdometryRefresher(odometry_pose)
        self.on_correction = on_correction
        self.latest = Latest()
        self.events: list[LoopEvent] = []
        self.use_process = cfg.pgo_process and threaded
        self._lock = threading.RLock()
        self._inflight: Future[PgoOutcome] | None = None
        self._executor: ProcessPoolExecutor | None = None
        if self.use_process:
            self._executor = ProcessPoolExecutor(max_workers=1, mp_context=mp.get_context("spawn"))
            self._executor.submit(_warm_up)

    # ------------------------------------------------------------------ stage
    def process(self, msg: Any) -> None:
        if not isinstance(msg, Keyframe):
            return
        with self._lock:
            for k, pose in self.refresher.refreshed().items():
                self.closer.update_odometry(k, pose)
            odom = self.refresher.new_keyframe(msg.keyframe_id, msg.world_from_body_vo)
            event = self.closer.add_keyframe(msg, odom)
            if event is not None:
                self.events.append(event)
                log.info(
                    "loop %s: keyframe %d -> %d (%d inliers) %s",
                    event.status,
                    event.query_kf_id,
                    event.match_kf_id,
                    event.inliers,
                    event.reason,
                )
            self._maybe_submit()

    def _maybe_submit(self) -> None:
        """Start an optimisation when a loop waits and none runs (call under the lock)."""
        if not self.closer.needs_pgo or self._inflight is not None:
            return
        request = self.closer.pgo_request()
        if self._executor is None:
            self._publish(self.closer.apply_pgo(run_pgo(request)))
            return
        future = self._executor.submit(run_pgo, request)
        self._inflight = future
        future.add_done_callback(self._done)

    def _done(self, future: Future[PgoOutcome]) -> None:
        try:
            outcome = future.result()
        except Exception as exc:  # reported with the stage's name
            self.error = StageError(self.name, exc, "")
            log.error("%s", self.error)
            with self._lock:
                self._inflight = None
            return
        with self._lock:
            self._inflight = None
            correction = self.closer.apply_pgo(outcome)
            self._maybe_submit()
        self._publish(correction)

    def _publish(self, correction: LoopCorrection) -> None:
        self.latest.set(correction)
        self.on_correction(correction)

    def on_end(self) -> None:
        """Wait for the running (and any queued) optimisation, then stop the worker."""
        while True:
            with self._lock:
                future = self._inflight
            if future is None:
                break
            try:
                future.result(timeout=300)
            except Exception:
                break
            while self._inflight is future:  # its callback (which may queue the next) runs now
                time.sleep(0.005)
        if self._executor is not None:
            self._executor.shutdown(wait=True, cancel_futures=True)
        with self._lock:
            if self.smoothed is not None:
                self.closer.exclude_from_adjustment = before_first_smoothed(
                    self.closer.kf_ids, self.smoothed
                )
            self.closer.global_adjustment()

    def abort(self) -> None:
        super().abort()
        if self._executor is not None:
            self._executor.shutdown(wait=False, cancel_futures=True)

    # ------------------------------------------------------------------ outputs
    def keyframe_corrections(self) -> dict[int, np.ndarray]:
        """Per keyframe id: corrected pose @ inverse(odometry pose) (identity before any loop)."""
        with self._lock:
            return self.closer.keyframe_map_from_odom()

    def keyframe_times_and_segments(self) -> tuple[dict[int, int], dict[int, int]]:
        """Keyframe id -> t_ns, and keyframe id -> map segment, of every keyframe seen."""
        with self._lock:
            return dict(self.closer.t_ns_of), dict(self.closer.segment_of)

    def corrected_keyframe_poses(self) -> dict[int, np.ndarray]:
        with self._lock:
            return self.closer.corrected_poses()

    def stats(self) -> dict[str, Any]:
        with self._lock:
            out: dict[str, Any] = dict(self.closer.stats.summary())
            out["mode"] = "process" if self.use_process else "inline"
            ba = self.closer.global_ba
            out["global_ba"] = None if ba is None else ba.summary()
            out["loops"] = [
                {
                    "loop_id": r.loop_id,
                    "query_kf": r.query_kf_id,
                    "match_kf": r.match_kf_id,
                    "inliers": r.inliers,
                    "t_ns": r.t_ns,
                    "query_t_ns": self.closer.t_ns_of.get(r.query_kf_id),
                    "match_t_ns": self.closer.t_ns_of.get(r.match_kf_id),
                    "active": r.active,
                }
                for r in self.closer.loops
            ]
            out["rejections"] = [
                {"query_kf": e.query_kf_id, "match_kf": e.match_kf_id, "reason": e.reason}
                for e in self.events
                if e.status == "rejected"
            ][:50]
            out["relocalisation"] = self.relocaliser.stats()
            out["invalid_odometry_poses"] = self.refresher.invalid_poses
            out["odometry_frame_jumps"] = self.refresher.frame_jumps
            if self.cfg.debug_graph:
                out["graph"] = self.closer.graph_dump()
        return out

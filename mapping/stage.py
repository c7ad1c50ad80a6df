"""The dense mapper as a pipeline stage: keyframes in, mesh out, in a worker process.

Plane sweep and TSDF fusion are heavy numpy/OpenCV work; in a worker process they never stall
the front end. This stage (a thread of the main process) forwards keyframes with their pose at
creation, drops a keyframe when the worker is more than ``max_backlog`` keyframes behind (the
lag is counted and reported, never queued without bound: :meth:`MapperStage.stats` gives
``keeps_up``, the dropped count and fraction, and per keyframe ``lag_behind_s``, how far in
sequence time the mapper trails the newest keyframe, and ``lag_wall_s``, arrival to report, as
p50/p90/p99/max), and receives per-keyframe reports and
periodic mesh snapshots (for rerun). At the end, keyframe poses are replaced by the final
(back-end optimised, loop-closed) ones: the mapper **re-integrates** the keyframes that moved
(de-integrate with the old pose, integrate with the new), then writes ``mesh.ply``.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from mapping.config import MapperStageConfig
from slam.calibration import Calibration
from slam.messages import EndOfStream, Keyframe, MapperReport, MeshSnapshot
from slam.stage import Stage, StageError, latency_summary
from slam.worker import READY, WorkerProcess, receive

log = logging.getLogger(__name__)


@dataclass(frozen=True, eq=False)
class _MapKeyframe:
    t_ns: int
    image_left: np.ndarray
    image_right: np.ndarray | None
    world_from_cam0: np.ndarray


@dataclass(frozen=True, eq=False)
class _Finish:
    world_from_cam0_by_t: dict[int, np.ndarray]
    mesh_path: str | None


@dataclass
class _MapperSummary:
    fused: int = 0
    skipped_static: int = 0
    reintegrated: int = 0
    vertices: int = 0
    faces: int = 0
    mesh_path: str | None = None
    final_ms: float = 0.0
    error: str | None = None
    depth_ms: list[float] = field(default_factory=list)
    fusion_ms: list[float] = field(default_factory=list)


def _make_mapper(calib: Calibration, cfg: MapperStageConfig) -> Any:
    from mapping.mapper import DenseMapper, MapperConfig
    from mapping.planesweep import SweepConfig
    from mapping.tsdf import TsdfConfig

    config = MapperConfig(
        tsdf=TsdfConfig(voxel_m=cfg.voxel_m, max_depth_m=cfg.max_depth_m),
        sweep=SweepConfig(
            depth_min_m=0.4,
            depth_max_m=8.0,
            num_planes=cfg.num_planes,
            threads=cfg.sweep_threads,
        ),
        depth_scale=cfg.depth_scale,
    )
    return DenseMapper.from_calibration(calib, config)


def _snapshot(mapper: Any, t_ns: int) -> MeshSnapshot | None:
    """The current mesh, or None while it is empty (``t_ns`` 0: the final mesh)."""
    mesh = mapper.mesh()
    if mesh.num_vertices == 0:
        return None
    return MeshSnapshot(t_ns, mesh.vertices_m, mesh.faces, mesh.normals, mesh.colors_rgb)


def _add(mapper: Any, item: _MapKeyframe) -> MapperReport:
    r = mapper.add_keyframe(item.t_ns, item.image_left, item.image_right, item.world_from_cam0)
    return MapperReport(r.t_ns, r.skipped, r.depth_ms, r.fusion_ms, r.blocks)


def _finish(mapper: Any, request: _Finish) -> tuple[_MapperSummary, MeshSnapshot | None]:
    """Re-integrate with the final poses, extract the mesh, write the PLY."""
    t0 = time.perf_counter()
    poses = request.world_from_cam0_by_t
    moved = mapper.update_poses(poses) if poses else 0
    final = _snapshot(mapper, 0)
    summary = _MapperSummary(reintegrated=moved)
    if final is not None:
        summary.vertices, summary.faces = len(final.vertices_m), len(final.faces)
        if request.mesh_path:
            from mapping.ply import write_ply_mesh

            write_ply_mesh(
                request.mesh_path, final.vertices_m, final.faces, final.normals, final.colors_rgb
            )
            summary.mesh_path = request.mesh_path
    summary.final_ms = (time.perf_counter() - t0) * 1e3
    return summary, final


def _worker(calib: Calibration, cfg: MapperStageConfig, inbox: Any, outbox: Any) -> None:
    """The worker process: fuse keyframes, report, snapshot meshes, finish with mesh.ply."""
    if cfg.sweep_threads > 1:
        # The sweep's own threads take whole strips; OpenCV's pool inside each call on top of
        # them only adds dispatch overhead (752x480, 64 planes, 2 views: 282-294 -> 270-276 ms).
        cv2.setNumThreads(1)
    try:
        mapper = _make_mapper(calib, cfg)
    except Exception as exc:
        outbox.put(RuntimeError(f"mapper start failed: {type(exc).__name__}: {exc}"))
        return
    outbox.put(READY)
    last_mesh = time.perf_counter()
    while True:
        msg = receive(inbox)
        try:
            if isinstance(msg, _MapKeyframe):
                outbox.put(_add(mapper, msg))
                if time.perf_counter() - last_mesh > cfg.mesh_every_s:
                    snap = _snapshot(mapper, msg.t_ns)
                    if snap is not None:
                        outbox.put(snap)
                    last_mesh = time.perf_counter()
            elif isinstance(msg, _Finish):
                summary, final = _finish(mapper, msg)
                if final is not None:
                    outbox.put(final)
                outbox.put(summary)
            elif isinstance(msg, EndOfStream):
                break
        except Exception as exc:  # reported by the stage with its name
            outbox.put(RuntimeError(f"{type(exc).__name__}: {exc}"))
            break


class MapperStage(Stage):
    """Forwards keyframes to the mapper worker and collects its reports and meshes."""

    def __init__(
        self,
        calib: Calibration,
        cfg: MapperStageConfig,
        on_mesh: Callable[[MeshSnapshot], None],
        threaded: bool,
        idle_worker: bool = False,
    ):
        """``idle_worker``: run the worker process under SCHED_IDLE (:func:`lower_priority`)."""
        super().__init__("mapper", maxsize=256, threaded=threaded)
        self.cfg = cfg
        self.calib = calib
        self.on_mesh = on_mesh
        self.body_from_cam0 = calib.cameras[0].body_from_cam
        self.sent: list[int] = []
        self.reports: list[MapperReport] = []
        self.received = 0
        self.newest_t_ns = 0
        self.dropped_lag = 0
        self.max_backlog_seen = 0
        self.max_lag_s = 0.0
        self._sent_wall: dict[int, float] = {}
        self.lag_wall_ms: list[float] = []
        """Per processed keyframe: wall time from its arrival here to its report (queue + work)."""
        self.lag_behind_ms: list[float] = []
        """Per processed keyframe: sequence time from it to the newest keyframe that had arrived
        when its report came back (how far behind the live front the mapper is)."""
        self.summary = _MapperSummary()
        self._lock = threading.Lock()
        self._done = threading.Event()
        self.use_process = threaded
        if self.use_process:
            self._worker = WorkerProcess(
                "mapper",
                _worker,
                (calib, cfg),
                self._on_worker_item,
                self._on_worker_died,
                nice=10,  # the lowest priority of the pipeline: it only has to keep up on average
                idle=idle_worker,
            )
        else:
            self._mapper = _make_mapper(calib, cfg)

    # -- results -------------------------------------------------------------------------
    def _handle_output(self, item: Any) -> bool:
        """Returns True when the worker has finished."""
        if isinstance(item, MapperReport):
            now = time.perf_counter()
            with self._lock:
                self.reports.append(item)
                behind_s = max(self.newest_t_ns - item.t_ns, 0) * 1e-9
                self.max_lag_s = max(self.max_lag_s, behind_s)
                self.lag_behind_ms.append(behind_s * 1e3)
                sent_at = self._sent_wall.pop(item.t_ns, None)
                if sent_at is not None:
                    self.lag_wall_ms.append((now - sent_at) * 1e3)
        elif isinstance(item, MeshSnapshot):
            self.on_mesh(item)
        elif isinstance(item, _MapperSummary):
            with self._lock:
                self.summary = item
            return True
        elif isinstance(item, Exception):
            self.error = StageError(self.name, item, "")
            log.error("%s", self.error)
            return True
        return False

    def _on_worker_item(self, item: Any) -> bool:
        finished = self._handle_output(item)
        if finished:
            self._done.set()
        return finished

    def _on_worker_died(self) -> None:
        if not self._done.is_set() and self.error is None:
            self.error = StageError(self.name, RuntimeError("the mapper worker process died"), "")
        self._done.set()

    # -- stage -----------------------------------------------------------------------------
    def process(self, msg: Any) -> None:
        if not isinstance(msg, Keyframe):
            return
        pose = msg.world_from_body_vo @ self.body_from_cam0
        item = _MapKeyframe(msg.t_ns, msg.image_left, msg.image_right, pose)
        with self._lock:
            self.received += 1
            self.newest_t_ns = max(self.newest_t_ns, msg.t_ns)
            backlog = len(self.sent) - len(self.reports)
        if not self.use_process:
            self.sent.append(msg.t_ns)
            self._sent_wall[msg.t_ns] = time.perf_counter()
            self._handle_output(_add(self._mapper, item))
            return
        self.max_backlog_seen = max(self.max_backlog_seen, backlog)
        if backlog >= self.cfg.max_backlog:
            self.dropped_lag += 1
            return
        with self._lock:
            self.sent.append(msg.t_ns)
            self._sent_wall[msg.t_ns] = time.perf_counter()
        self._worker.put(item)

    def finish(self, final_world_from_body: dict[int, np.ndarray], mesh_path: Path | None) -> None:
        """Re-integrate with the final keyframe poses (by t_ns) and write ``mesh_path``."""
        fused = set(self.sent)
        poses = (
            {
                int(t): np.asarray(p) @ self.body_from_cam0
                for t, p in final_world_from_body.items()
                if int(t) in fused
            }
            if self.cfg.final_reintegration
            else {}
        )
        request = _Finish(poses, None if mesh_path is None else str(mesh_path))
        if not self.use_process:
            self.summary, final = _finish(self._mapper, request)
            if final is not None:
                self.on_mesh(final)
            return
        if not self._worker.is_alive():
            return
        self._worker.put(request)
        self._done.wait(timeout=600)
        self._worker.stop(receive_timeout_s=10)

    def abort(self) -> None:
        super().abort()
        if self.use_process:
            self._worker.terminate()

    def stats(self) -> dict[str, Any]:
        """The ``mapping`` section of stats.json (lags in seconds, see the module docstring)."""
        with self._lock:
            reports = list(self.reports)
            lag_wall, lag_behind = list(self.lag_wall_ms), list(self.lag_behind_ms)
        fused = [r for r in reports if not r.skipped]

        def seconds(summary: dict[str, float]) -> dict[str, float]:
            return {
                k.replace("_ms", "_s"): (v / 1e3 if k != "count" else v) for k, v in summary.items()
            }

        return {
            "mode": "process" if self.use_process else "in-process",
            "keeps_up": self.dropped_lag == 0,
            "keyframes_received": self.received,
            "dropped_fraction": self.dropped_lag / max(self.received, 1),
            "lag_behind_s": seconds(latency_summary(lag_behind)),
            "lag_wall_s": seconds(latency_summary(lag_wall)),
            "keyframes_sent": len(self.sent),
            "keyframes_fused": len(fused),
            "keyframes_skipped_static": len(reports) - len(fused),
            "keyframes_dropped_lag": self.dropped_lag,
            "max_backlog": self.max_backlog_seen,
            "max_lag_s": self.max_lag_s,
            "depth": latency_summary([r.depth_ms for r in fused]),
            "fusion": latency_summary([r.fusion_ms for r in fused]),
            "final_reintegrated": self.summary.reintegrated,
            "final_ms": self.summary.final_ms,
            "mesh_vertices": self.summary.vertices,
            "mesh_faces": self.summary.faces,
            "mesh_path": self.summary.mesh_path,
        }

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

During the run, loop corrections move the map too: new keyframes arrive at their pose in the
corrected map (``map_from_odom`` of their segment), and the keyframes a correction moved are
sent as a :class:`MapPoseUpdate`; the core re-integrates ``reintegrate_per_keyframe`` of them
after each keyframe, so the live mesh follows the loop closure without stalling the mapper.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from mapping.config import MapperStageConfig
from slam.core.calibration import Calibration
from slam.core.latency import latency_summary
from slam.core.messages import (
    Keyframe,
    LoopCorrection,
    MapFinish,
    MapKeyframe,
    MapperReport,
    MapperSummary,
    MapPoseUpdate,
    MeshSnapshot,
)
from slam.runtime.worker import ProcessStage, WorkerCore

log = logging.getLogger(__name__)


def _make_mapper(calib: Calibration, cfg: MapperStageConfig) -> Any:
    from mapping.mapper import DenseMapper, MapperConfig
    from mapping.planesweep import SweepConfig
    from mapping.tsdf import TsdfConfig

    config = MapperConfig(
        tsdf=TsdfConfig(
            voxel_m=cfg.voxel_m, max_depth_m=cfg.max_depth_m, threads=cfg.sweep_threads
        ),
        sweep=SweepConfig(
            depth_min_m=0.4,
            depth_max_m=8.0,
            num_planes=cfg.num_planes,
            threads=cfg.sweep_threads,
        ),
        depth_scale=cfg.depth_scale,
        depth_method=cfg.depth_method,
    )
    return DenseMapper.from_calibration(calib, config)


def spread_order(n: int) -> list[int]:
    """0..n-1 in bit-reversed order: every prefix is spread evenly over the range (0, n/2,
    n/4, 3n/4, ...), so a budget that runs out leaves gaps everywhere, not one long gap."""
    if n <= 0:
        return []
    bits = max(1, (n - 1).bit_length())
    order = [int(format(i, f"0{bits}b")[::-1], 2) for i in range(1 << bits)]
    return [i for i in order if i < n]


def _landmark_depth_range(kf: Keyframe, world_from_cam0: np.ndarray) -> tuple[float, float] | None:
    """(2nd, 98th) percentile depth (m) in cam0 of the keyframe's tracked landmarks; None with
    fewer than 20 in front of the camera."""
    pts = np.asarray(kf.points_world_vo, float)
    if len(pts) == 0:
        return None
    cam0_from_world = np.linalg.inv(world_from_cam0)
    z = pts @ cam0_from_world[2, :3] + cam0_from_world[2, 3]
    z = z[np.isfinite(z) & (z > 0.05)]
    if len(z) < 20:
        return None
    lo, hi = np.percentile(z, [2, 98])
    return float(lo), float(hi)


def _snapshot(mapper: Any, t_ns: int) -> MeshSnapshot | None:
    """The current mesh, or None while it is empty (``t_ns`` 0: the final mesh)."""
    mesh = mapper.mesh()
    if mesh.num_vertices == 0:
        return None
    return MeshSnapshot(t_ns, mesh.vertices_m, mesh.faces, mesh.normals, mesh.colors_rgb)


def _add(
    mapper: Any, item: MapKeyframe, pending: dict[int, np.ndarray], n_moves: int
) -> MapperReport:
    """Fuse a keyframe, then re-integrate up to ``n_moves`` keyframes of ``pending`` (oldest
    correction first; taken out of it)."""
    cpu0 = time.process_time()
    r = mapper.add_keyframe(
        item.t_ns,
        item.image_left,
        item.image_right,
        item.world_from_cam0,
        landmark_depth_range_m=item.landmark_depth_range_m,
    )
    moved = 0
    if pending and n_moves > 0:
        batch = {t: pending.pop(t) for t in list(pending)[:n_moves]}
        moved = mapper.update_poses(batch)
    cpu_ms = 1e3 * (time.process_time() - cpu0)
    return MapperReport(r.t_ns, r.skipped, r.depth_ms, r.fusion_ms, r.blocks, moved, cpu_ms)


def _finish(mapper: Any, request: MapFinish) -> tuple[MapperSummary, MeshSnapshot | None]:
    """Re-integrate with the final poses, extract the mesh, write the PLY."""
    t0 = time.perf_counter()
    poses = request.world_from_cam0_by_t
    moved = mapper.update_poses(poses) if poses else 0
    final = _snapshot(mapper, 0)
    summary = MapperSummary(reintegrated=moved)
    if final is not None:
        summary.vertices, summary.faces = len(final.vertices_m), len(final.faces)
        if request.mesh_path:
            from datasets.ply import write_ply_mesh

            write_ply_mesh(
                request.mesh_path, final.vertices_m, final.faces, final.normals, final.colors_rgb
            )
            summary.mesh_path = request.mesh_path
    summary.final_ms = (time.perf_counter() - t0) * 1e3
    return summary, final


class MapperCore(WorkerCore):
    """The dense mapper behind the stage: fuses keyframes, reports, snapshots meshes."""

    def __init__(self, calib: Calibration, cfg: MapperStageConfig, live_mesh: bool = True):
        """``live_mesh``: send periodic mesh snapshots (only worth it when a viewer shows them:
        marching cubes over the whole map holds up the keyframes behind it)."""
        self.live_mesh = live_mesh
        if cfg.depth_method == "sgbm":
            cv2.setNumThreads(cfg.sweep_threads)  # StereoSGBM's rows in OpenCV's pool
        elif cfg.sweep_threads > 1:
            # The sweep's own threads take whole strips; OpenCV's pool inside each call on top
            # of them only adds dispatch overhead (752x480, 64 planes, 2 views: 282-294 ->
            # 270-276 ms).
            cv2.setNumThreads(1)
        self.cfg = cfg
        self.mapper = _make_mapper(calib, cfg)
        self.mapper.volume.warm_up()  # before the first keyframe, not during it
        self.last_mesh = time.perf_counter()
        self.pending_poses: dict[int, np.ndarray] = {}
        """Loop-corrected keyframe poses not re-integrated yet (t_ns -> world_from_cam0)."""

    def handle(self, msg: Any) -> list[Any]:
        if isinstance(msg, MapKeyframe):
            out: list[Any] = [
                _add(self.mapper, msg, self.pending_poses, self.cfg.reintegrate_per_keyframe)
            ]
            if self.live_mesh and time.perf_counter() - self.last_mesh > self.cfg.mesh_every_s:
                snap = _snapshot(self.mapper, msg.t_ns)
                if snap is not None:
                    out.append(snap)
                self.last_mesh = time.perf_counter()
            return out
        if isinstance(msg, MapPoseUpdate):
            for t in msg.world_from_cam0_by_t:  # a newer correction goes to the back
                self.pending_poses.pop(t, None)
            self.pending_poses.update(msg.world_from_cam0_by_t)
            return []
        if isinstance(msg, MapFinish):
            self.pending_poses.clear()  # the final poses supersede them
            summary, final = _finish(self.mapper, msg)
            return [summary] if final is None else [final, summary]
        return []


def _make_core(calib: Calibration, cfg: MapperStageConfig, live_mesh: bool) -> MapperCore:
    return MapperCore(calib, cfg, live_mesh)


class MapperStage(ProcessStage):
    """Forwards keyframes to the mapper core, collects its reports and emits its meshes."""

    end_timeout_s = 600.0  # the final re-integration and mesh

    def __init__(
        self,
        calib: Calibration,
        cfg: MapperStageConfig,
        threaded: bool,
        idle_worker: bool = False,
        live_mesh: bool = True,
        pausable: bool = False,
    ):
        """``idle_worker``: run the worker process under SCHED_IDLE (``slam.runtime.priority``);
        ``live_mesh``: snapshots for a viewer (see :class:`MapperCore`); ``pausable``: the
        front end may stop the worker while it tracks a frame (:meth:`paused_while_working`)."""
        super().__init__(
            "mapper",
            256,
            threaded,
            _make_core,
            (calib, cfg, live_mesh),
            role="mapper",
            idle=idle_worker,
            pausable=pausable,
        )
        self.pausable = pausable and self.use_process
        self.paused_frames = 0
        """Front-end frames during which the worker was stopped (it had work)."""
        self.cfg = cfg
        self.calib = calib
        self.body_from_cam0 = calib.cameras[0].body_from_cam
        self.sent: list[int] = []
        self.reports: list[MapperReport] = []
        self.received = 0
        self.newest_t_ns = 0
        self.dropped_lag = 0
        self.max_backlog_seen = 0
        self.max_lag_s = 0.0
        self.held: list[MapKeyframe] = []
        """Dropped keyframes that showed something new: fused at the end (``catch_up_*``)."""
        self.caught_up = 0
        self._sent_poses: list[np.ndarray] = []
        self._held_count: list[int] = []
        """Per held keyframe: its number among the new views dropped (see :meth:`_hold`)."""
        self._new_views_dropped = 0
        self._hold_stride = 1
        self.loop_corrections = 0
        self.loop_reintegrated = 0
        self.map_from_odom: dict[int, np.ndarray] = {}
        """Latest loop correction per map segment (odometry -> corrected map)."""
        self._t_by_keyframe_id: dict[int, int] = {}
        self._sent_wall: dict[int, float] = {}
        self.lag_wall_ms: list[float] = []
        """Per processed keyframe: wall time from its arrival here to its report (queue + work)."""
        self.lag_behind_ms: list[float] = []
        """Per processed keyframe: sequence time from it to the newest keyframe that had arrived
        when its report came back (how far behind the live front the mapper is)."""
        self.summary = MapperSummary()
        self._summary_seen = threading.Event()
        self._lock = threading.Lock()

    @contextmanager
    def paused_while_working(self) -> Iterator[None]:
        """Stop the worker process for the duration (the front end's frame) if it has a
        keyframe to work on; a waiting worker is left alone (it takes nothing from anyone).

        Why: a SCHED_IDLE mapper still slows the front end on this 2-core VM. Interleaved in
        one run (hall, ``--speed 1``, load 8-9), front-end frames with the mapper working
        beside them against frames with it stopped: latency p90 42 against 25 ms, run-queue
        wait mean 10.7 against 5.8 ms (likely: a preempted front end stays queued on its
        core, and a core running SCHED_IDLE work never goes idle to pull it over), the rest
        ("GIL") p99 13 against 7 ms (it holds hypervisor steal: the host sees no guest
        priorities).
        BENCHMARKS.md, "Front end's p99 with the mapper: stopped during frames"."""
        proc = self._proc
        stop = False
        if self.pausable and proc is not None and self.error is None:
            with self._lock:
                working = len(self.sent) > len(self.reports)
            stop = working and proc.pause()
        try:
            yield
        finally:
            if stop:
                assert proc is not None
                proc.resume()
                self.paused_frames += 1

    # -- results -------------------------------------------------------------------------
    def on_output(self, item: Any) -> None:
        if isinstance(item, MapperReport):
            now = time.perf_counter()
            with self._lock:
                self.reports.append(item)
                self.loop_reintegrated += item.reintegrated
                behind_s = max(self.newest_t_ns - item.t_ns, 0) * 1e-9
                self.max_lag_s = max(self.max_lag_s, behind_s)
                self.lag_behind_ms.append(behind_s * 1e3)
                sent_at = self._sent_wall.pop(item.t_ns, None)
                if sent_at is not None:
                    self.lag_wall_ms.append((now - sent_at) * 1e3)
        elif isinstance(item, MeshSnapshot):
            self.emit(item, block=True if item.t_ns == 0 else None)  # the final mesh gets in
        elif isinstance(item, MapperSummary):
            with self._lock:
                self.summary = item
            self._summary_seen.set()

    # -- stage -----------------------------------------------------------------------------
    def process(self, msg: Any) -> None:
        if isinstance(msg, LoopCorrection):
            self.loop_corrections += 1
            self.map_from_odom.update(msg.map_from_odom)
            with self._lock:
                fused = set(self.sent)
            poses = {
                t: np.asarray(msg.corrected_keyframe_poses[k]) @ self.body_from_cam0
                for k, t in self._t_by_keyframe_id.items()
                if k in msg.corrected_keyframe_poses and t in fused
            }
            if poses and self.cfg.reintegrate_per_keyframe > 0 and self.error is None:
                self.send(MapPoseUpdate(poses))
            return
        if not isinstance(msg, Keyframe) or not msg.metric:
            return  # (a monocular keyframe before the scale is known)
        pose_odom = msg.world_from_body_vo @ self.body_from_cam0
        depth_range = _landmark_depth_range(msg, pose_odom)  # landmarks: odometry world
        pose = self.map_from_odom.get(msg.segment_id, np.eye(4)) @ pose_odom
        item = MapKeyframe(msg.t_ns, msg.image_left, msg.image_right, pose, depth_range)
        self._t_by_keyframe_id[msg.keyframe_id] = msg.t_ns
        with self._lock:
            self.received += 1
            self.newest_t_ns = max(self.newest_t_ns, msg.t_ns)
            backlog = len(self.sent) - len(self.reports)
        self.max_backlog_seen = max(self.max_backlog_seen, backlog)
        if self.use_process and backlog >= self.cfg.max_backlog:
            self.dropped_lag += 1
            if self.cfg.catch_up_max_keyframes > 0 and self._is_new_view(pose):
                self._hold(item)
            return
        self._send_keyframe(item)

    def _send_keyframe(self, item: MapKeyframe) -> None:
        with self._lock:
            self.sent.append(item.t_ns)
            self._sent_wall[item.t_ns] = time.perf_counter()
        self._sent_poses.append(item.world_from_cam0)
        self.send(item)

    def _hold(self, item: MapKeyframe) -> None:
        """Hold a dropped new view for the catch-up. The hold keeps every ``stride``-th of
        them; when it is full the stride doubles and the held ones off the new stride go, so
        the hold stays an even subsample of the whole run, never just its first part."""
        n = self._new_views_dropped
        self._new_views_dropped += 1
        if n % self._hold_stride:
            return
        if len(self.held) >= self.cfg.catch_up_max_keyframes:
            self._hold_stride *= 2
            keep = [i for i, c in enumerate(self._held_count) if c % self._hold_stride == 0]
            self.held = [self.held[i] for i in keep]
            self._held_count = [self._held_count[i] for i in keep]
            if n % self._hold_stride:
                return
        self.held.append(item)
        self._held_count.append(n)

    def _is_new_view(self, world_from_cam0: np.ndarray) -> bool:
        """Whether a pose is farther (or more rotated) than the catch-up thresholds from every
        keyframe sent or held."""
        poses = self._sent_poses + [h.world_from_cam0 for h in self.held]
        if not poses:
            return True
        stack = np.asarray(poses)
        dist = np.linalg.norm(stack[:, :3, 3] - world_from_cam0[:3, 3], axis=1)
        # angle between the optical axes (the view direction is what decides what is seen)
        cos = np.clip(stack[:, :3, 2] @ world_from_cam0[:3, 2], -1.0, 1.0)
        near = (dist < self.cfg.catch_up_min_distance_m) & (
            np.degrees(np.arccos(cos)) < self.cfg.catch_up_min_angle_deg
        )
        return not bool(near.any())

    def _catch_up(self, final_world_from_cam0: dict[int, np.ndarray]) -> None:
        """Fuse the held keyframes (at their final poses where known) within ``catch_up_s``,
        in an order that spreads them over the run (see :func:`spread_order`), one in flight
        at a time so that the budget is kept."""
        deadline = time.monotonic() + self.cfg.catch_up_s
        for k in spread_order(len(self.held)):
            if time.monotonic() > deadline or self.error is not None or self.final_seen.is_set():
                break
            h = self.held[k]
            pose = final_world_from_cam0.get(h.t_ns, h.world_from_cam0)
            n_reports = len(self.reports)
            self._send_keyframe(
                MapKeyframe(h.t_ns, h.image_left, h.image_right, pose, h.landmark_depth_range_m)
            )
            while len(self.reports) == n_reports and time.monotonic() < deadline + 30.0:
                if self.error is not None or self.final_seen.is_set():
                    break
                time.sleep(0.005)
            self.caught_up += 1
        self.held.clear()
        self._held_count.clear()

    def on_end(self) -> None:
        """The worker stays up for :meth:`finish` (the final poses are known only later)."""

    def finish(
        self, final_world_from_body: dict[int, np.ndarray] | None, mesh_path: Path | None
    ) -> None:
        """Re-integrate with the final keyframe poses (by t_ns; None: none, e.g. after an
        interruption), write ``mesh_path``, end the worker."""
        fused = set(self.sent)
        poses = (
            {
                int(t): np.asarray(p) @ self.body_from_cam0
                for t, p in final_world_from_body.items()
                if int(t) in fused
            }
            if self.cfg.final_reintegration and final_world_from_body
            else {}
        )
        if self.error is None and not self.final_seen.is_set():
            self.begin_end()
            if self.held and final_world_from_body is not None:
                self._catch_up(
                    {
                        int(t): np.asarray(p) @ self.body_from_cam0
                        for t, p in final_world_from_body.items()
                    }
                )
            self.send(MapFinish(poses, None if mesh_path is None else str(mesh_path)))
            deadline = time.monotonic() + self.end_timeout_s
            while not self._summary_seen.wait(0.1) and time.monotonic() < deadline:
                if self.final_seen.is_set() or (self.abandon and self.abandon.is_set()):
                    break
        self.end_worker()

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
            "loop_corrections_received": self.loop_corrections,
            "loop_reintegrated": self.loop_reintegrated,
            "keeps_up": self.dropped_lag == 0,
            "keyframes_received": self.received,
            "dropped_fraction": self.dropped_lag / max(self.received, 1),
            "lag_behind_s": seconds(latency_summary(lag_behind)),
            "lag_wall_s": seconds(latency_summary(lag_wall)),
            "keyframes_sent": len(self.sent),
            "keyframes_fused": len(fused),
            "keyframes_skipped_static": len(reports) - len(fused),
            "keyframes_dropped_lag": self.dropped_lag,
            "keyframes_caught_up": self.caught_up,
            "paused_frames": self.paused_frames,
            "max_backlog": self.max_backlog_seen,
            "max_lag_s": self.max_lag_s,
            "depth": latency_summary([r.depth_ms for r in fused]),
            "fusion": latency_summary([r.fusion_ms for r in fused]),
            # CPU per fused keyframe (depth, fusion, re-integrations): only the worker process
            # measures the mapper alone.
            "cpu_per_keyframe": (
                latency_summary([r.cpu_ms for r in fused]) if self.use_process else None
            ),
            "final_reintegrated": self.summary.reintegrated,
            "final_ms": self.summary.final_ms,
            "mesh_vertices": self.summary.vertices,
            "mesh_faces": self.summary.faces,
            "mesh_path": self.summary.mesh_path,
        }

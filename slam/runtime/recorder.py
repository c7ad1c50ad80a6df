"""The recorder: what the run's outputs are made of, collected from the stages' messages.

It is a consumer like a stage (``put``) but does no work of its own: the front end's
:class:`TrackingResult`, the back end's :class:`BackendOutput` events and the loop closer's
:class:`LoopCorrection` are kept (thread-safe) for the outputs, the summary and stats.json.
"""

from __future__ import annotations

import threading
from typing import Any

import numpy as np

from slam.core.geometry import invert_transform
from slam.core.latency import latency_summary
from slam.core.messages import BackendOutput, FrontendCorrection, LoopCorrection, TrackingResult
from slam.core.trajectory import Trajectory
from slam.runtime.outputs import trajectory_from_poses


class Recorder:
    """Collects per-frame results and events for the outputs (thread-safe)."""

    def __init__(self, start_ns: int) -> None:
        self._lock = threading.Lock()
        self.start_ns = start_ns
        self.poses: list[tuple[int, np.ndarray]] = []  # odometry
        self.map_poses: list[tuple[int, np.ndarray]] = []  # live, loop-corrected, as published
        self.map_jumps: list[dict[str, float]] = []
        self.pose_segments: list[int] = []
        # (index in ``poses`` of the first pose in the new world, new_from_old): the front
        # end's corrections after its change of frame
        self.world_changes: list[tuple[int, np.ndarray]] = []
        self.keyframes: list[tuple[int, np.ndarray]] = []
        self.frontend_latency_ms: list[float] = []
        self.frontend_cpu_ms: list[float] = []
        self.frontend_runqueue_ms: list[float] = []  # empty where the OS does not report it
        self.frontend_gil_ms: list[float] = []  # latency - CPU - run queue, where reported
        self.states: dict[str, int] = {}
        self.last_state = ""
        self.keyframe_times: dict[int, int] = {}
        self.events: list[tuple[int, str]] = []
        self.initialised_after_s: float | None = None
        self.camera_stamped: set[int] = set()  # frames stamped before the time offset was known

    # -- consumer ------------------------------------------------------------------------------
    def put(self, msg: Any, block: bool = True) -> bool:
        if isinstance(msg, TrackingResult):
            self._add(msg)
        elif isinstance(msg, FrontendCorrection):
            if msg.reframe:
                self._reframe(msg.new_from_old)
            else:
                with self._lock:
                    self.world_changes.append((len(self.poses), np.asarray(msg.new_from_old)))
        elif isinstance(msg, BackendOutput):
            est = msg.estimate
            t_ns = est.t_ns if est is not None else 0
            for text in msg.events:
                self.event(t_ns, text)
                if "initialised" in text and self.initialised_after_s is None:
                    self.initialised_after_s = (t_ns - self.start_ns) * 1e-9
        elif isinstance(msg, LoopCorrection):
            self.event(
                msg.t_ns,
                f"loop closed: keyframe {msg.query_keyframe_id} -> {msg.match_keyframe_id} "
                f"({msg.inliers} inliers)",
            )
        return True

    def _add(self, res: TrackingResult) -> None:
        with self._lock:
            self.frontend_latency_ms.append(res.latency_ms)
            self.frontend_cpu_ms.append(res.cpu_ms)
            if res.runqueue_ms >= 0:
                self.frontend_runqueue_ms.append(res.runqueue_ms)
                self.frontend_gil_ms.append(max(res.latency_ms - res.cpu_ms - res.runqueue_ms, 0.0))
            self.states[res.state] = self.states.get(res.state, 0) + 1
            self.last_state = res.state
            if res.world_from_body is not None:
                if res.time_offset_ns == 0:
                    self.camera_stamped.add(res.t_ns)
                self.poses.append((res.t_ns, res.world_from_body))
                live = res.map_from_body if res.map_from_body is not None else res.world_from_body
                self.map_poses.append((res.t_ns, live))
                if res.map_jump_m > 0 or res.map_jump_deg > 0:
                    self.map_jumps.append(
                        {
                            "t_ns": res.t_ns,
                            "map_generation": res.map_generation,
                            "metres": res.map_jump_m,
                            "degrees": res.map_jump_deg,
                        }
                    )
                    self.events.append(
                        (
                            res.t_ns,
                            f"live pose corrected by loop closure: {res.map_jump_m * 100:.1f} cm, "
                            f"{res.map_jump_deg:.2f} deg",
                        )
                    )
                self.pose_segments.append(res.segment_id)
                if res.is_keyframe:
                    self.keyframes.append((res.t_ns, res.world_from_body))
                    self.keyframe_times[res.keyframe_id] = res.t_ns

    def _reframe(self, new_from_old: np.ndarray) -> None:
        """Re-express every pose recorded so far in a new world frame (the back end's
        gravity-aligned world, at its initialisation)."""
        with self._lock:
            self.poses = [(t, new_from_old @ p) for t, p in self.poses]
            self.map_poses = [(t, new_from_old @ p) for t, p in self.map_poses]
            self.keyframes = [(t, new_from_old @ p) for t, p in self.keyframes]
            old_from_new = invert_transform(new_from_old)
            self.world_changes = [
                (i, new_from_old @ c @ old_from_new) for i, c in self.world_changes
            ]

    def event(self, t_ns: int, text: str) -> None:
        with self._lock:
            self.events.append((t_ns, text))

    # -- reading -------------------------------------------------------------------------------
    def keyframe_times_copy(self) -> dict[int, int]:
        """Keyframe id -> t_ns of every keyframe recorded so far."""
        with self._lock:
            return dict(self.keyframe_times)

    def segments_of_first(self, n: int) -> np.ndarray:
        """Map segment of each of the first ``n`` recorded poses (poses are only appended)."""
        with self._lock:
            return np.array(self.pose_segments[:n])

    def frontend_breakdown(self) -> dict[str, dict[str, float]]:
        """Latency summaries of the front end's CPU time, wait (latency - CPU) and, of that
        wait, run-queue time (runnable without a CPU) and the rest: waiting for the GIL (or
        sleeping, ``slam.cputime``), ``frontend_frame_gil``."""
        with self._lock:
            lat = np.asarray(self.frontend_latency_ms)
            cpu = np.asarray(self.frontend_cpu_ms)
            rq = list(self.frontend_runqueue_ms)
            gil = list(self.frontend_gil_ms)
        out = {
            "frontend_frame_cpu": latency_summary(cpu.tolist()),
            "frontend_frame_wait": latency_summary(np.maximum(lat - cpu, 0.0).tolist()),
        }
        if rq:
            out["frontend_frame_runqueue"] = latency_summary(rq)
            out["frontend_frame_gil"] = latency_summary(gil)
        return out

    def frontend_latencies_ms(self) -> list[float]:
        """The front end's latency of every frame so far."""
        with self._lock:
            return list(self.frontend_latency_ms)

    def snapshot(self) -> tuple[Trajectory, Trajectory]:
        """Every frame's pose and every keyframe's, as recorded so far."""
        with self._lock:
            poses, kfs = list(self.poses), list(self.keyframes)
        return trajectory_from_poses(poses), trajectory_from_poses(kfs)

    def continuous_odometry(self, n: int) -> np.ndarray:
        """The first ``n`` recorded odometry poses (n, 4, 4), each taken back into the world of
        the first one by undoing the front end's corrections since (map reuse, re-anchoring on
        the back end's estimates; not its change of frame): a chain without their jumps, whose
        motion between two frames is the tracking's (the landmarks a re-anchoring sets to the
        back end's estimates make it so only approximately)."""
        with self._lock:
            poses = np.array([p for _, p in self.poses[:n]], dtype=float).reshape(-1, 4, 4)
            changes = list(self.world_changes)
        first_from_world = np.eye(4)
        for k, (start, new_from_old) in enumerate(changes):
            end = changes[k + 1][0] if k + 1 < len(changes) else len(poses)
            first_from_world = first_from_world @ invert_transform(new_from_old)
            if start < end:
                poses[start:end] = first_from_world @ poses[start:end]
        return poses

    def correction_frames(self, n: int) -> np.ndarray:
        """Indices (< ``n``) of the first poses recorded in a world the front end had just
        moved (its corrections after its change of frame), increasing."""
        with self._lock:
            starts = {i for i, _ in self.world_changes if i < n}
        return np.array(sorted(starts), dtype=np.int64)

    def live(self) -> Trajectory:
        """Every frame's live pose in the loop-corrected map, as published so far."""
        with self._lock:
            poses = list(self.map_poses)
        return trajectory_from_poses(poses)

    def in_imu_clock(self, traj: Trajectory, offset_ns: int) -> Trajectory:
        """``traj`` with the frames stamped before the back end knew the camera-IMU offset
        (camera stamps) moved into the IMU clock by ``offset_ns`` (the offset known at the end):
        every output row then says when, in the IMU's clock, its image was taken. Poses are
        not touched; a row that would no longer be after its predecessor is left out."""
        if offset_ns == 0 or len(traj) == 0:
            return traj
        with self._lock:
            early = np.array(sorted(self.camera_stamped), dtype=np.int64)
        t_ns = np.asarray(traj.t_ns, np.int64)
        t_new = np.where(np.isin(t_ns, early), t_ns + int(offset_ns), t_ns)
        # a row is kept when it is after every row before it (a left-out row is never after
        # the last kept one, so the running maximum of all rows is that of the kept ones)
        before = np.maximum.accumulate(t_new)[:-1]
        keep = np.concatenate([[True], t_new[1:] > before])
        return Trajectory(t_new[keep], traj.positions_m[keep], traj.q_wxyz[keep])

    def map_jump_summary(self) -> dict[str, Any]:
        """The loop corrections' jumps of the live pose (stats.json ``live_map_corrections``)."""
        with self._lock:
            jumps = list(self.map_jumps)
        return {
            "count": len(jumps),
            "max_m": max((j["metres"] for j in jumps), default=0.0),
            "max_deg": max((j["degrees"] for j in jumps), default=0.0),
            "jumps": jumps,
        }

"""Ending a run and reporting it: stages ended in order within bounded time, the end-of-run
work timed on its own, stats.json and the output files.

The run's real-time factor is the tracking's: sequence time over the wall time until the front
end has answered the last frame. The end-of-run work (the back end's last updates, the loop
closer's global adjustment, the mapper's re-integration and mesh) comes after it and is
reported beside it (``end_of_run_s`` and its parts), never folded in.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

from datasets.sequence import Sequence
from slam.config import SlamConfig, config_to_yaml
from slam.core.latency import latency_summary
from slam.core.messages import ImuBatch
from slam.core.trajectory import Trajectory
from slam.cputime import machine_cpu_since, machine_cpu_ticks
from slam.frontend.tracker import FrontendStats
from slam.runtime.control import RunControl
from slam.runtime.end_of_run import (
    final_keyframe_poses,
    keyframe_trajectory,
    loop_closed_trajectory,
)
from slam.runtime.memory import TreeMemory
from slam.runtime.outputs import RunOutputs
from slam.runtime.player import PlayState, real_time_factor
from slam.runtime.stage import Stage, StageError
from slam.runtime.viewer import ViewerSession

if TYPE_CHECKING:
    from slam.runtime.wiring import Pipeline


@dataclass
class RunTimes:
    """Wall-clock marks of a run (``time.perf_counter`` seconds)."""

    t_wall0: float
    tracking_end: float | None = None  # the front end answered its last frame
    end: float | None = None  # every output written
    parts_s: dict[str, float] = field(default_factory=dict)  # end-of-run work by stage

    def tracking_s(self, now: float) -> float:
        return (self.tracking_end or now) - self.t_wall0


@dataclass
class RunResult:
    """What a run produced."""

    out_dir: Path | None
    trajectory: Trajectory  # the odometry (trajectory_odometry.tum)
    keyframes: Trajectory
    stats: dict[str, Any]
    interrupted: bool = False
    error: StageError | None = None
    warnings: list[str] = field(default_factory=list)
    loop_closed: Trajectory | None = None
    exit_code: int = 0  # 128 + the signal that stopped the run, else 0
    session: ViewerSession | None = None  # the viewer, for serving the final map after the run
    live: Trajectory | None = None  # the live pose in the loop-corrected map (trajectory.tum)


def _smoothed(p: Pipeline) -> Callable[[int], bool]:
    """Whether the back end estimated a keyframe (always, without a back end)."""
    backend = p.backend
    return lambda kid: backend is None or kid in backend.keyframe_poses


def _trajectories(
    p: Pipeline, imu: ImuBatch | None = None, gravity_m_s2: float = 9.81
) -> tuple[Trajectory, Trajectory, Trajectory | None]:
    """Odometry, keyframe and loop-closed trajectories as of now (``imu``: the run's IMU, at
    its end, for the loop-closed frames between keyframes, with the back end's biases)."""
    traj, kfs = p.recorder.snapshot()
    kfs = keyframe_trajectory(kfs, p.backend, p.recorder)
    biases = None if p.backend is None else p.backend.biases_at
    closed = (
        None
        if p.loop is None
        else loop_closed_trajectory(
            traj,
            p.loop,
            _smoothed(p),
            p.recorder,
            imu,
            gravity_m_s2,
            biases,
            None if p.backend is None else p.backend.imu_intrinsics(),
        )
    )
    return traj, kfs, closed


def _end_stage(stage: Stage, control: RunControl, began_s: float | None = None) -> float:
    """Close ``stage`` and wait for it (until ``control.abandon``); the seconds it took.
    ``began_s``: when the run's end began (``EndOfStream.run_end_began_s``)."""
    t0 = time.perf_counter()
    stage.close(end_began_s=began_s)
    while not stage.join(timeout=0.2):
        if control.abandon.is_set():
            stage.abort()
            break
    return round(time.perf_counter() - t0, 3)


@dataclass
class Run:
    """One run being played: its pipeline and everything its report is made of."""

    p: Pipeline
    seq: Sequence
    cfg: SlamConfig
    out_dir: Path | None
    control: RunControl
    memory: TreeMemory
    state: PlayState = field(default_factory=PlayState)
    times: RunTimes = field(default_factory=lambda: RunTimes(t_wall0=time.perf_counter()))
    machine_cpu0: tuple[int, int, int] | None = field(default_factory=machine_cpu_ticks)
    """The machine's CPU ticks when the run began (stats.json ``machine_cpu``)."""
    _outputs: RunOutputs | None = field(default=None, init=False, repr=False)

    def stats(self, error: StageError | None) -> dict[str, Any]:
        """stats.json as of now."""
        p, state, times, cfg = self.p, self.state, self.times, self.cfg
        now = time.perf_counter()
        fe = p.frontend.frontend.stats
        tracking_s = times.tracking_s(now)
        end_s = None if times.tracking_end is None else (times.end or now) - times.tracking_end
        roles = {pid: s.name for s in p.stages if (pid := getattr(s, "worker_pid", None))}
        mem = self.memory.summary(roles)
        return {
            "sequence": self.seq.name,
            "preset": cfg.preset,
            "frames_in": state.frames_in,
            "frames_processed": fe.frames,
            "frames_tracked": fe.tracked,
            "frames_dropped": state.frames_dropped,
            "frames_lost": fe.lost_frames,
            "tracking_losses": fe.tracking_losses,
            "map_segments": fe.segments,
            "keyframes": fe.keyframes,
            "blur_pose_fused": fe.blur_pose_fused,
            "sequence_duration_s": state.sequence_s,
            "real_time_factor": real_time_factor(state.sequence_s, tracking_s),
            "tracking_wall_s": tracking_s,
            "end_of_run_s": end_s,
            "end_of_run_parts_s": dict(times.parts_s),
            "wall_time_s": (times.end or now) - times.t_wall0,
            "speed": cfg.player.speed,
            "sequential": cfg.player.sequential,
            "latency": {
                "frontend_frame": latency_summary(p.recorder.frontend_latencies_ms()),
                "frontend_after_pose": latency_summary(fe.after_pose_ms),
                **p.recorder.frontend_breakdown(),
                **{f"stage_{s.name}": s.latency_stats() for s in p.stages},
            },
            # The whole machine since the start (other processes too): a busy machine, or a
            # hypervisor stealing time, explains slow frames (``slam.cputime``).
            "machine_cpu": machine_cpu_since(self.machine_cpu0),
            "peak_rss_mb": mem["total_peak_mb"],
            "memory": mem,
            "loop_closure": None if p.loop is None else p.loop.stats(),
            "mapping": None if p.mapper is None else p.mapper.stats(),
            "live_map_corrections": p.recorder.map_jump_summary(),
            "map_reuse": map_reuse_summary(fe),
            "frame_states": dict(p.recorder.states),
            "relocalisations": fe.relocalisations,
            "imu_bridged_losses": fe.imu_bridged,
            "track_refits": {"attempted": fe.track_refits, "kept": fe.track_refits_kept},
            "klt_predicted": {"tracks": fe.klt_predicted, "retracked": fe.klt_retracked},
            "backend": None
            if p.backend is None
            else {
                "mode": "process" if p.backend.use_process else "in-process",
                "update": p.backend.update_stats(),
                "initialised_after_s": p.recorder.initialised_after_s,
                "keyframes_waited_for_imu": p.backend.keyframes_waited_for_imu,
                "keyframes_not_covered_by_imu": p.backend.keyframes_not_covered_by_imu,
                **p.backend.final_stats,
            },
            "events": [
                {"t_ns": t, "event": e} for t, e in sorted(fe.state_log + p.recorder.events)
            ],
            "sequence_warnings": list(self.seq.warnings),
            "interrupted": self.control.stop.is_set(),
            "stopped_by": self.control.signal_name or None,
            "stages_timed_out": [s.name for s in p.stages if getattr(s, "timed_out", False)],
            "error": str(error) if error else None,
        }

    def write(
        self,
        traj: Trajectory,
        kfs: Trajectory,
        closed: Trajectory | None,
        stats: dict[str, Any],
    ) -> None:
        """Write every output (atomically, file by file); nothing without an output folder.
        ``trajectory.tum`` is the live pose as published (loop-corrected as known then),
        ``trajectory_odometry.tum`` the odometry ``traj``."""
        if self.out_dir is None:
            return
        rec, offset_ns = self.p.recorder, self._time_offset_ns()
        traj, kfs = rec.in_imu_clock(traj, offset_ns), rec.in_imu_clock(kfs, offset_ns)
        extra = {"trajectory_odometry": traj}
        if closed is not None:
            extra["trajectory_loop_closed"] = rec.in_imu_clock(closed, offset_ns)
        live = rec.in_imu_clock(rec.live(), offset_ns)
        if self._outputs is None:
            self._outputs = RunOutputs(self.out_dir, config_to_yaml(self.cfg))
        self._outputs.write(live, kfs, stats, extra)

    def _time_offset_ns(self) -> int:
        """The camera-IMU offset the back end applies (0: none, or not estimated online)."""
        backend = self.p.backend
        if backend is None or not self.cfg.backend.time_offset_online:
            return 0
        return backend.time_offset_ns()

    def _imu_for_the_end(self) -> tuple[ImuBatch | None, float]:
        """The sequence's IMU (and gravity) when the run used it, else (None, 9.81)."""
        calib = self.seq.calibration.imu
        if self.p.backend is None or calib is None:  # a back end exactly when the IMU is used
            return None, 9.81
        imu = self.seq.imu()
        return ImuBatch(imu.t_ns, imu.gyro_rad_s, imu.accel_m_s2), calib.gravity_m_s2

    def flush(self) -> None:
        """The outputs for what has been processed so far (every few seconds of a run)."""
        if self.out_dir is not None:
            self.write(*_trajectories(self.p), self.stats(None))

    def end(self, progress: bool) -> RunResult:
        """End every stage in wiring order (bounded), do the end-of-run work, write the
        outputs."""
        p, control, times = self.p, self.control, self.times
        interrupted = control.stop.is_set()
        if interrupted:
            for s in p.stages:
                s.interrupt()
        _end_stage(p.frontend, control)
        times.tracking_end = time.perf_counter()
        if p.backend is not None:
            times.parts_s["backend"] = _end_stage(p.backend, control)
            p.frontend.finish_frontend()  # a back-end initialisation after the last frame
        if p.loop is not None:
            if progress and not interrupted:
                print("loop closure: global adjustment ...", flush=True)
            times.parts_s["loop"] = _end_stage(p.loop, control, times.tracking_end)
        traj, kfs, closed = _trajectories(p, *self._imu_for_the_end())
        if p.mapper is not None:
            t0 = time.perf_counter()
            final = None
            if not interrupted and p.mapper.error is None:
                final = final_keyframe_poses(kfs, p.loop, closed, _smoothed(p), p.recorder)
                if progress:
                    print("dense mapping: final re-integration and mesh ...", flush=True)
            mesh = None if self.out_dir is None else Path(self.out_dir) / "mesh.ply"
            p.mapper.finish(final, mesh)
            _end_stage(p.mapper, control)
            times.parts_s["mapper"] = round(time.perf_counter() - t0, 3)
        if p.viewer is not None:
            p.viewer.close(timeout_s=5.0)
            p.viewer.join(timeout=5.0)  # a stuck viewer thread is a daemon: the run ends anyway
        error = self.state.error or next((s.error for s in p.stages if s.error is not None), None)
        times.end = time.perf_counter()
        self.memory.stop()
        stats = self.stats(error)
        self.write(traj, kfs, closed, stats)
        return RunResult(
            self.out_dir,
            traj,
            kfs,
            stats,
            interrupted,
            error,
            list(self.seq.warnings),
            closed,
            control.exit_code,
            live=p.recorder.live(),
        )


def map_reuse_summary(fe: FrontendStats) -> dict[str, Any]:
    """stats.json ``map_reuse``: the landmarks tracked again from the front end's map."""

    def share(part: int, whole: int) -> float | None:
        return part / whole if whole else None

    return {
        "searches": fe.map_searches,
        "candidates": fe.map_candidates,
        "found": fe.map_found,
        "reobserved": fe.map_reobserved,
        "rejected": fe.map_rejected,
        "corrections": fe.map_corrections,
        "correction_max_m": fe.map_correction_max_m,
        "old_landmark_fraction": share(fe.landmarks_tracked_old, fe.landmarks_tracked),
        "revisit_frames": fe.revisit_frames,
        "old_landmark_fraction_on_revisits": share(fe.revisit_landmarks_old, fe.revisit_landmarks),
    }

"""Wiring: which stage feeds which, every feedback path, and the player that drives them.

```
Sequence --Player--> ImuSample -> ImuBuffer (front end gyro prior) [+ back end queue]
                  -> StereoFrame -> FrontendStage --TrackingResult--> Recorder, RerunStage
                                                  --Keyframe--> [back end] -> Estimate (Latest)
Estimate (Latest) ----------------------------------> FrontEnd (read without waiting)
```

``run_slam`` plays a sequence at sensor rate (``speed`` 1), faster, or as fast as the pipeline
takes it (``speed`` 0), in concurrent (threads, frames dropped when the front end falls behind in
real-time playback) or sequential mode (one thread, deterministic). Outputs are flushed
atomically every few seconds and at the end, also after Ctrl-C or a stage failure.
"""

from __future__ import annotations

import logging
import resource
import sys
import threading
import time
from collections.abc import Generator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from datasets.prefetch import prefetched_messages
from datasets.sequence import Sequence
from mapping.stage import MapperStage
from slam.backend_stage import BackendStage
from slam.config import SlamConfig, config_to_yaml
from slam.frontend.tracker import FrontEnd
from slam.imu_buffer import ImuBuffer
from slam.loop.stage import LoopClosureStage
from slam.loop.worker import LoopClosureWorkerStage
from slam.messages import (
    BackendOutput,
    ImuBatch,
    ImuSample,
    Keyframe,
    MeshSnapshot,
    StereoFrame,
    TrackingResult,
)
from slam.output import trajectory_from_poses, write_run_outputs
from slam.stage import Latest, Stage, StageError, latency_summary
from slam.trajectory import Trajectory

log = logging.getLogger(__name__)

FLUSH_EVERY_S = 5.0


class Recorder:
    """Collects per-frame results for the outputs (thread-safe)."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self.poses: list[tuple[int, np.ndarray]] = []
        self.pose_segments: list[int] = []
        self.keyframes: list[tuple[int, np.ndarray]] = []
        self.frontend_latency_ms: list[float] = []
        self.frontend_cpu_ms: list[float] = []
        self.frontend_runqueue_ms: list[float] = []  # empty where the OS does not report it
        self.states: dict[str, int] = {}
        self.last_state = ""
        self.keyframe_times: dict[int, int] = {}
        self.events: list[tuple[int, str]] = []

    def add(self, res: TrackingResult) -> None:
        with self._lock:
            self.frontend_latency_ms.append(res.latency_ms)
            self.frontend_cpu_ms.append(res.cpu_ms)
            if res.runqueue_ms >= 0:
                self.frontend_runqueue_ms.append(res.runqueue_ms)
            self.states[res.state] = self.states.get(res.state, 0) + 1
            self.last_state = res.state
            if res.world_from_body is not None:
                self.poses.append((res.t_ns, res.world_from_body))
                self.pose_segments.append(res.segment_id)
                if res.is_keyframe:
                    self.keyframes.append((res.t_ns, res.world_from_body))
                    self.keyframe_times[res.keyframe_id] = res.t_ns

    def reframe(self, new_from_old: np.ndarray) -> None:
        """Re-express every pose recorded so far in a new world frame."""
        with self._lock:
            self.poses = [(t, new_from_old @ p) for t, p in self.poses]
            self.keyframes = [(t, new_from_old @ p) for t, p in self.keyframes]

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
        wait, run-queue time (runnable without a CPU); the rest of the wait is the GIL or
        sleeping (``slam.cputime``)."""
        with self._lock:
            lat = np.asarray(self.frontend_latency_ms)
            cpu = np.asarray(self.frontend_cpu_ms)
            rq = list(self.frontend_runqueue_ms)
        out = {
            "frontend_frame_cpu": latency_summary(cpu.tolist()),
            "frontend_frame_wait": latency_summary(np.maximum(lat - cpu, 0.0).tolist()),
        }
        if rq:
            out["frontend_frame_runqueue"] = latency_summary(rq)
        return out

    def event(self, t_ns: int, text: str) -> None:
        with self._lock:
            self.events.append((t_ns, text))

    def snapshot(self) -> tuple[Trajectory, Trajectory, list[float]]:
        with self._lock:
            poses, kfs, lat = list(self.poses), list(self.keyframes), list(self.frontend_latency_ms)
        return trajectory_from_poses(poses), trajectory_from_poses(kfs), lat


class FrontendStage(Stage):
    """Runs the front end on each frame and fans its outputs out."""

    def __init__(
        self,
        frontend: FrontEnd,
        recorder: Recorder,
        keyframe_consumers: list[Stage],
        viewer: Stage | None,
        threaded: bool,
        queue_size: int,
    ):
        super().__init__("frontend", maxsize=queue_size, threaded=threaded)
        self.frontend = frontend
        self.recorder = recorder
        self.keyframe_consumers = keyframe_consumers
        self.viewer = viewer

    def process(self, msg: Any) -> None:
        assert isinstance(msg, StereoFrame)
        result, keyframe = self.frontend.process(msg)
        self.recorder.add(result)
        if keyframe is not None:
            for consumer in self.keyframe_consumers:
                consumer.put(keyframe)
        if self.viewer is not None:
            self.viewer.put(result, block=False)  # the viewer may drop; the front end never waits
            if keyframe is not None:
                self.viewer.put(keyframe, block=False)


@dataclass
class RunResult:
    """What a run produced."""

    out_dir: Path | None
    trajectory: Trajectory
    keyframes: Trajectory
    stats: dict[str, Any]
    interrupted: bool = False
    error: StageError | None = None
    warnings: list[str] = field(default_factory=list)
    loop_closed: Trajectory | None = None


def peak_rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0  # Linux reports KiB


def run_slam(
    seq: Sequence,
    cfg: SlamConfig,
    out_dir: Path | None = None,
    rerun_mode: str = "none",
    progress: bool = True,
) -> RunResult:
    """Play ``seq`` through the pipeline and write the run's outputs to ``out_dir``."""
    from slam.viz import RerunStage, open_recording

    sequential = cfg.player.sequential
    threaded = not sequential
    imu_buffer = ImuBuffer() if cfg.use_imu and seq.num_imu else None
    latest_estimate = Latest()
    recorder = Recorder()
    rec = open_recording(rerun_mode)
    viewer = (
        RerunStage(rec, seq.calibration, cfg.viz, seq.ground_truth, threaded=threaded)
        if rec is not None
        else None
    )
    frontend = FrontEnd(
        seq.calibration, cfg.frontend, imu_buffer, latest_estimate.get, recorder.reframe
    )
    loop_stage: LoopClosureStage | LoopClosureWorkerStage | None = None
    keyframe_consumers: list[Stage] = []
    imu_consumers: list[Stage] = []
    backend: BackendStage | None = None
    init_time: dict[str, float] = {}
    if cfg.use_imu and seq.calibration.imu is not None and seq.num_imu:

        def on_backend_output(out: BackendOutput) -> None:
            est = out.estimate
            t_ns = est.t_ns if est is not None else 0
            for text in out.events:
                recorder.event(t_ns, text)
                if "initialised" in text and "t_s" not in init_time:
                    init_time["t_s"] = (t_ns - seq.start_ns()) * 1e-9
                if viewer is not None:
                    viewer.put(("log", text), block=False)
            if viewer is not None and est is not None:
                viewer.put(est, block=False)

        backend = BackendStage(
            seq.calibration,
            cfg.backend,
            latest_estimate,
            on_backend_output,
            threaded,
            cfg.backend_process,
        )
        keyframe_consumers.append(backend)
        imu_consumers.append(backend)
    mapper: MapperStage | None = None
    if cfg.mapping.enabled:

        def on_mesh(snapshot: MeshSnapshot) -> None:
            if viewer is not None:
                viewer.put(snapshot, block=snapshot.t_ns == 0)  # the final mesh always gets in

        mapper = MapperStage(
            seq.calibration, cfg.mapping, on_mesh, threaded, cfg.player.idle_workers
        )
        keyframe_consumers.append(mapper)
    if cfg.loop_closure:
        from slam.loop.viz import log_loop_correction
        from slam.messages import LoopCorrection

        def on_loop_correction(corr: LoopCorrection) -> None:
            recorder.event(
                corr.t_ns,
                f"loop closed: keyframe {corr.query_keyframe_id} -> {corr.match_keyframe_id} "
                f"({corr.inliers} inliers)",
            )
            if viewer is not None and rec is not None:
                viewer.put(("loop", corr), block=False)

        def odometry_pose(kid: int) -> np.ndarray | None:
            """Back-end pose of a keyframe, else the front end's current belief of it (which
            follows the frame change at initialisation; Keyframe.world_from_body_vo does not)."""
            pose = None if backend is None else backend.keyframe_poses.get(kid)
            return pose if pose is not None else frontend.kf_poses.get(kid)

        def smoothed(kid: int) -> bool:
            """Whether the back end estimated the keyframe (after its initialisation)."""
            return backend is None or kid in backend.keyframe_poses

        loop_stage = (
            LoopClosureWorkerStage(
                seq.calibration,
                cfg.loop,
                odometry_pose,
                on_loop_correction,
                cfg.player.idle_workers,
                smoothed,
            )
            if threaded
            else LoopClosureStage(
                seq.calibration,
                cfg.loop,
                odometry_pose,
                on_loop_correction,
                threaded,
                smoothed=smoothed,
            )
        )
        loop_stage.nice = 10  # background work: never at the front end's expense
        keyframe_consumers.append(loop_stage)
        frontend.relocaliser = loop_stage.relocaliser
        if viewer is not None:
            viewer.loop_logger = log_loop_correction
    fe_stage = FrontendStage(
        frontend, recorder, keyframe_consumers, viewer, threaded, cfg.player.frame_queue_size
    )
    stages: list[Stage] = [fe_stage, *keyframe_consumers]
    if viewer is not None:
        stages.append(viewer)
    switch_interval_s = sys.getswitchinterval()
    if threaded and cfg.player.gil_switch_interval_ms > 0:
        sys.setswitchinterval(cfg.player.gil_switch_interval_ms * 1e-3)  # restored at the end
    for s in stages:
        s.start()

    stats: dict[str, Any] = {}
    frames_in = frames_dropped = 0
    interrupted = False
    error: StageError | None = None
    t_wall0 = time.perf_counter()
    t_first_ns: int | None = None
    t_last_ns = 0
    last_flush = t_wall0
    speed = cfg.player.speed
    total = (
        seq.num_frames if not cfg.player.max_frames else min(cfg.player.max_frames, seq.num_frames)
    )
    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=total, unit="frame", desc=f"slam run {seq.name}", leave=True)

    def make_stats() -> dict[str, Any]:
        wall = time.perf_counter() - t_wall0
        seq_s = (t_last_ns - (t_last_ns if t_first_ns is None else t_first_ns)) * 1e-9
        _, _, lat = recorder.snapshot()
        fe = frontend.stats
        return {
            "sequence": seq.name,
            "preset": cfg.preset,
            "frames_in": frames_in,
            "frames_processed": fe.frames,
            "frames_tracked": fe.tracked,
            "frames_dropped": frames_dropped,
            "frames_lost": fe.lost_frames,
            "tracking_losses": fe.tracking_losses,
            "map_segments": fe.segments,
            "keyframes": fe.keyframes,
            "sequence_duration_s": seq_s,
            "wall_time_s": wall,
            "real_time_factor": seq_s / wall if wall > 0 else 0.0,
            "speed": speed,
            "sequential": sequential,
            "latency": {
                "frontend_frame": latency_summary(lat),
                **recorder.frontend_breakdown(),
                **{f"stage_{s.name}": s.latency_stats() for s in stages},
            },
            "peak_rss_mb": peak_rss_mb(),
            "peak_rss_children_mb": resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 1024.0,
            "loop_closure": None if loop_stage is None else loop_stage.stats(),
            "mapping": None if mapper is None else mapper.stats(),
            "relocalisations": fe.relocalisations,
            "imu_bridged_losses": fe.imu_bridged,
            "track_refits": {"attempted": fe.track_refits, "kept": fe.track_refits_kept},
            "backend": None
            if backend is None
            else {
                "mode": "process" if backend.use_process else "in-process",
                "update": backend.update_stats(),
                "initialised_after_s": init_time.get("t_s"),
                **backend.final_stats,
            },
            "events": [{"t_ns": t, "event": e} for t, e in sorted(fe.state_log + recorder.events)],
            "sequence_warnings": list(seq.warnings),
            "interrupted": interrupted,
            "error": str(error) if error else None,
        }

    def keyframe_trajectory(frontend_kfs: Trajectory) -> Trajectory:
        """Back-end (optimised) keyframe poses where there are any, else the front end's."""
        if backend is None or not backend.keyframe_poses:
            return frontend_kfs
        times = recorder.keyframe_times_copy()
        poses = sorted((times[k], p) for k, p in dict(backend.keyframe_poses).items() if k in times)
        return trajectory_from_poses(poses)

    def loop_closed(traj: Trajectory) -> dict[str, Trajectory]:
        """The loop-closed trajectory (every frame through its keyframe's correction)."""
        if loop_stage is None or len(traj) == 0:
            return {}
        from slam.geometry import invert_transform
        from slam.loop.closer import loop_closed_poses

        corrections = dict(loop_stage.keyframe_corrections())
        corrected = loop_stage.corrected_keyframe_poses()
        t_ns_of, segment_of = loop_stage.keyframe_times_and_segments()
        kids = [k for k in corrections if k in t_ns_of]
        # Keyframes from before the back end's initialisation only have the front end's
        # pre-gravity-alignment pose, and their odometry edge carries the change of frame
        # (measured on room-figure8: kf 0 and 1 corrected 41 mm off): frames of that time
        # follow the first initialised keyframe instead.
        kids = [k for k in kids if smoothed(k)] or kids
        # A keyframe's correction relative to the *output* pose of its own frame where there is
        # one: frames then follow their keyframe by the causal relative motion they were tracked
        # with. (Relative to the keyframe's back-end pose, each frame also carried the
        # difference between the causal and the smoothed estimate of the keyframe: measured
        # on room-figure8 after global BA, 5.6 mm frame ATE against 4.0 mm for the keyframes.)
        frame_at = {int(t): i for i, t in enumerate(traj.t_ns.tolist())}
        frame_poses = traj.matrices()
        for k in kids:
            i = frame_at.get(int(t_ns_of[k]))
            if i is not None and k in corrected:
                corrections[k] = corrected[k] @ invert_transform(frame_poses[i])
        kf_t = np.array([t_ns_of[k] for k in kids], dtype=np.int64)
        kf_seg = np.array([segment_of[k] for k in kids])
        if not kids:
            return {}
        segments = recorder.segments_of_first(len(traj))
        poses = loop_closed_poses(
            traj.t_ns,
            segments,
            traj.matrices(),
            kf_t,
            kf_seg,
            np.array([corrections[k] for k in kids]),
        )
        return {"trajectory_loop_closed": Trajectory.from_matrices(traj.t_ns, poses)}

    def flush() -> None:
        if out_dir is None:
            return
        traj, kfs, _ = recorder.snapshot()
        write_run_outputs(
            out_dir,
            traj,
            keyframe_trajectory(kfs),
            make_stats(),
            config_to_yaml(cfg),
            loop_closed(traj),
        )

    imu_pending: list[ImuSample] = []

    def flush_imu() -> None:
        """The IMU samples since the last frame, to the buffer and the IMU consumers at once."""
        if not imu_pending:
            return
        if imu_buffer is not None:
            imu_buffer.extend(imu_pending)
        if imu_consumers:
            batch = ImuBatch.from_samples(imu_pending)
            for consumer in imu_consumers:
                consumer.put(batch)
        imu_pending.clear()

    messages = (
        prefetched_messages(seq, idle=cfg.player.idle_workers)
        if threaded and cfg.player.reader_process
        else iter(seq.messages())
    )
    try:
        for msg in messages:
            if t_first_ns is None:
                t_first_ns = msg.t_ns
            if isinstance(msg, ImuSample):
                imu_pending.append(msg)  # handed on with the next frame, in one message
                continue
            if speed > 0:  # paced per frame (IMU samples wait for their frame anyway)
                ahead = (msg.t_ns - t_first_ns) * 1e-9 / speed - (time.perf_counter() - t_wall0)
                if ahead > 0:
                    time.sleep(ahead)
            flush_imu()
            if cfg.player.max_frames and frames_in >= cfg.player.max_frames:
                break
            frames_in += 1
            t_last_ns = msg.t_ns
            accepted = fe_stage.put(msg, block=sequential or speed <= 0)
            if not accepted:
                frames_dropped += 1
            failed = next((s.error for s in stages if s.error is not None), None)
            if failed is not None:
                error = failed
                break
            if bar is not None:
                bar.update(1)
                if frames_in % 10 == 0:
                    wall = time.perf_counter() - t_wall0
                    seq_s = (t_last_ns - t_first_ns) * 1e-9
                    bar.set_postfix(
                        rtf=f"{seq_s / max(wall, 1e-9):.2f}",
                        state=recorder.last_state,
                        dropped=frames_dropped,
                        refresh=False,
                    )
            now = time.perf_counter()
            if now - last_flush > FLUSH_EVERY_S:
                flush()
                last_flush = now
    except KeyboardInterrupt:
        interrupted = True
        for s in stages:
            s.abort()
    finally:
        if isinstance(messages, Generator):
            messages.close()  # stops the reader process when the loop ended early
        for s in stages:  # in wiring order: upstream stages finish before their consumers
            if s is not viewer:
                s.close()
                s.join()
        frontend.finish()  # a back-end initialisation published after the last frame
        if bar is not None:
            bar.close()
        traj, kfs, _ = recorder.snapshot()
        kfs = keyframe_trajectory(kfs)
        extra = loop_closed(traj)
        if mapper is not None and not interrupted and mapper.error is None:
            final = {int(t): p for t, p in zip(kfs.t_ns, kfs.matrices(), strict=True)}
            if loop_stage is not None:
                times = recorder.keyframe_times_copy()
                closed = extra.get("trajectory_loop_closed")
                closed_at = (
                    {}
                    if closed is None
                    else dict(zip(closed.t_ns.tolist(), closed.matrices(), strict=True))
                )
                for kid, pose in loop_stage.corrected_keyframe_poses().items():
                    if kid not in times:
                        continue
                    # Before the back end's initialisation the pose graph's pose was 35 mm off
                    # on room-figure8: take the loop-closed trajectory's frame there.
                    use = pose if smoothed(kid) else closed_at.get(int(times[kid]))
                    if use is not None:
                        final[times[kid]] = use
            if progress:
                print("dense mapping: final re-integration and mesh ...", flush=True)
            mapper.finish(final, None if out_dir is None else Path(out_dir) / "mesh.ply")
        if viewer is not None:
            viewer.close()
            viewer.join()
        sys.setswitchinterval(switch_interval_s)
        if error is None:
            error = next((s.error for s in stages if s.error is not None), None)
        if rec is not None:
            rec.flush()
            rec.disconnect()
        stats = make_stats()
        if out_dir is not None:
            write_run_outputs(out_dir, traj, kfs, stats, config_to_yaml(cfg), extra)
    return RunResult(
        out_dir,
        traj,
        kfs,
        stats,
        interrupted,
        error,
        list(seq.warnings),
        extra.get("trajectory_loop_closed"),
    )


__all__ = ["RunResult", "run_slam", "Keyframe"]

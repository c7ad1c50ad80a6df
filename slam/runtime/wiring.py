"""Wiring: build the stages, connect them, run the player, end the run in order.

```
Player --StereoFrame--> FrontendStage --TrackingResult--> Recorder, viewer
       --ImuBatch--> ImuBuffer (front end), BackendStage
FrontendStage --Keyframe--> BackendStage, MapperStage, LoopClosureStage, viewer
              --FrontendCorrection--> Recorder, LoopClosureStage
BackendStage --Estimate (Latest)--> FrontEnd (read without waiting)
             --BackendOutput--> Recorder, LoopClosureStage, viewer
LoopClosureStage --LoopCorrection--> Recorder, MapperStage, viewer
MapperStage --MeshSnapshot--> viewer
```

``run_slam`` plays a sequence at sensor rate (``speed`` 1), faster, or as fast as the pipeline
takes it (``speed`` 0), concurrently (threads and worker processes) or sequentially (one
thread, deterministic). Outputs are written atomically every few seconds and at the end, also
after Ctrl-C, SIGTERM or a stage failure (``slam.runtime.control``).
"""

from __future__ import annotations

import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from datasets.cam0_only import Cam0Only
from datasets.sequence import Sequence
from slam.config import SlamConfig, check_run_config, validate_config
from slam.core.messages import (
    BackendOutput,
    FrontendCorrection,
    Keyframe,
    LoopCorrection,
    MeshSnapshot,
    TrackingResult,
)
from slam.frontend.mono import MonoFrontEnd
from slam.frontend.tracker import FrontEnd
from slam.imu_buffer import ImuBuffer
from slam.runtime.backend import BackendStage
from slam.runtime.control import RunControl, handle_stop_signals
from slam.runtime.frontend import FrontendStage
from slam.runtime.loop import LoopClosureStage
from slam.runtime.mapper import MapperStage
from slam.runtime.memory import TreeMemory
from slam.runtime.player import at_mid_exposure, play, restamped
from slam.runtime.priority import limit_blas_threads
from slam.runtime.reader import prefetched_messages
from slam.runtime.recorder import Recorder
from slam.runtime.report import Run, RunResult
from slam.runtime.stage import Latest, Stage
from slam.runtime.viewer import RerunStage, ViewerSession, open_recording

FLUSH_EVERY_S = 5.0


@dataclass
class Pipeline:
    """The built stages of one run (None where the configuration leaves a stage out)."""

    frontend: FrontendStage
    recorder: Recorder
    imu_buffer: ImuBuffer | None
    backend: BackendStage | None = None
    mapper: MapperStage | None = None
    loop: LoopClosureStage | None = None
    viewer: RerunStage | None = None
    imu_consumers: list[Stage] = field(default_factory=list)

    @property
    def stages(self) -> list[Stage]:
        """Every stage in wiring order: upstream stages end before their consumers."""
        chain = [self.frontend, self.backend, self.mapper, self.loop, self.viewer]
        return [s for s in chain if s is not None]


def build(seq: Sequence, cfg: SlamConfig, session: ViewerSession | None) -> Pipeline:
    """Build the stages ``cfg`` asks for and connect them (nothing runs yet)."""
    threaded = not cfg.player.sequential
    idle = cfg.player.idle_workers
    with_imu = cfg.use_imu and seq.calibration.imu is not None and seq.num_imu > 0
    imu_buffer = ImuBuffer() if cfg.use_imu and seq.num_imu else None
    latest_estimate = Latest()
    recorder = Recorder(seq.start_ns())
    viewer = None
    if session is not None:
        frame_times = seq.frame_times_ns()
        origin = int(frame_times[0]) if len(frame_times) else seq.start_ns()
        viewer = RerunStage(
            session.rec, seq.calibration, cfg.viz, seq.ground_truth, threaded, origin
        )
    loop = LoopClosureStage(seq.calibration, cfg.loop, threaded, idle) if cfg.loop_closure else None
    frontend = (MonoFrontEnd if cfg.monocular else FrontEnd)(
        seq.calibration,
        cfg.frontend,
        imu_buffer,
        latest_estimate.get,
        relocaliser=None if loop is None else loop.relocaliser,
    )
    map_source = None if loop is None else loop.latest.get
    p = Pipeline(
        FrontendStage(
            frontend,
            threaded,
            cfg.player.frame_queue_size,
            map_source,
            live_correction=cfg.loop.live_correction,
        ),
        recorder,
        imu_buffer,
    )
    p.loop, p.viewer = loop, viewer
    if with_imu:
        p.backend = BackendStage(
            seq.calibration,
            cfg.backend,
            latest_estimate,
            threaded,
            cfg.backend_process,
            publish_inertial=loop is not None and cfg.loop.global_ba and cfg.loop.global_ba_imu,
            estimate_delay_ns=round(cfg.player.sequential_estimate_delay_ms * 1e6),
        )
        p.imu_consumers.append(p.backend)
    if cfg.mapping.enabled:
        p.mapper = MapperStage(
            seq.calibration,
            cfg.mapping,
            threaded,
            idle or cfg.mapping.idle_worker,
            live_mesh=viewer is not None,
            pausable=cfg.mapping.pause_while_tracking and cfg.player.speed > 0,
        )
        if p.mapper.pausable:
            p.frontend.quiet = p.mapper.paused_while_working

    fe = p.frontend
    fe.connect(recorder, FrontendCorrection, TrackingResult)
    for consumer in (p.backend, p.mapper, p.loop):
        if consumer is not None:
            fe.connect(consumer, Keyframe)
    if loop is not None:
        fe.connect(loop, FrontendCorrection)
    if p.backend is not None:
        p.backend.connect(recorder, BackendOutput)
        if loop is not None:
            p.backend.connect(loop, BackendOutput)
    if loop is not None:
        loop.connect(recorder, LoopCorrection)
        if p.mapper is not None:
            loop.connect(p.mapper, LoopCorrection, block=False)
    if viewer is not None:
        fe.connect(viewer, TrackingResult, Keyframe, block=False)  # the viewer may drop
        for source, kind in ((p.backend, BackendOutput), (loop, LoopCorrection)):
            if source is not None:
                source.connect(viewer, kind, block=False)
        if p.mapper is not None:
            p.mapper.connect(viewer, MeshSnapshot, block=False)
    return p


def run_slam(
    seq: Sequence,
    cfg: SlamConfig,
    out_dir: Path | None = None,
    rerun_mode: str = "none",
    progress: bool = True,
    control: RunControl | None = None,
    keep_viewer: bool = False,
) -> RunResult:
    """Play ``seq`` through the pipeline and write the run's outputs to ``out_dir``.

    SIGINT and SIGTERM (main thread) end the run in order; the result says so
    (``interrupted``, ``exit_code``). ``keep_viewer``: a ``serve`` viewer's server outlives the
    run (``result.session.stop_server()`` ends it).
    """
    validate_config(cfg)  # again: callers may have changed it after loading
    check_run_config(cfg, seq.name, stereo=seq.calibration.is_stereo, has_imu=seq.has_imu)
    if cfg.monocular:
        seq = Cam0Only.of(seq)  # a stereo source read as mono: cam0 and the IMU
    control = control or RunControl()
    with handle_stop_signals(control):
        result = _run(seq, cfg, out_dir, rerun_mode, progress, control)
    if result.session is not None and not keep_viewer:
        result.session.stop_server()
    return result


def _run(
    seq: Sequence,
    cfg: SlamConfig,
    out_dir: Path | None,
    rerun_mode: str,
    progress: bool,
    control: RunControl,
) -> RunResult:
    memory = TreeMemory().start()
    session = open_recording(rerun_mode, out_dir)
    p = build(seq, cfg, session)
    for s in p.stages:
        s.abandon = control.abandon
    switch_interval_s = sys.getswitchinterval()
    threaded = not cfg.player.sequential
    if threaded and cfg.player.gil_switch_interval_ms > 0:
        sys.setswitchinterval(cfg.player.gil_switch_interval_ms * 1e-3)  # restored at the end
    for s in p.stages:
        s.start()
    # The output flushes convert rotations with scipy: imported lazily, its first import took
    # the GIL for a few hundred ms at the first flush, 5 s into the run, while the front end
    # waited. Import it while the workers start up instead.
    import scipy.spatial.transform  # noqa: F401

    run = Run(p, seq, cfg, out_dir, control, memory)
    total = (
        seq.num_frames if not cfg.player.max_frames else min(cfg.player.max_frames, seq.num_frames)
    )
    bar: Any = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=total, unit="frame", desc=f"slam run {seq.name}", leave=True)
    if session is not None and session.web_url:
        print(f"rerun web viewer: {session.web_url}", flush=True)
    messages = (
        prefetched_messages(seq, idle=cfg.player.idle_workers)
        if threaded and cfg.player.reader_process
        else iter(seq.messages())
    )
    if cfg.player.mid_exposure:
        messages = at_mid_exposure(messages)
    if p.backend is not None and cfg.backend.time_offset_online:
        messages = restamped(messages, p.backend.time_offset_ns)
    blas = limit_blas_threads()  # this process's stages, until the run ends
    try:
        play(
            messages,
            p.frontend,
            p.imu_buffer,
            p.imu_consumers,
            p.stages,
            run.state,
            control,
            speed=cfg.player.speed,
            sequential=cfg.player.sequential,
            max_frames=cfg.player.max_frames,
            t_wall0=run.times.t_wall0,
            bar=bar,
            last_state=lambda: p.recorder.last_state,
            every_few_seconds=run.flush,
            flush_every_s=FLUSH_EVERY_S,
        )
    except KeyboardInterrupt:  # a run outside the main thread, or before the handler
        control.request_stop(2)
    finally:
        if bar is not None:
            bar.close()
        result = run.end(progress)
        sys.setswitchinterval(switch_interval_s)
        blas.restore_original_limits()
        if session is not None:
            session.close()
            result.session = session
    return result

"""Configuration of the live dense mapper (``mapping`` in the run config).

Config only: ``slam.config`` nests it without importing the mapper stage
or anything heavy.
"""

from __future__ import annotations

from dataclasses import dataclass

from slam.core.bounds import bounded
from slam.core.errors import SlamError

DEPTH_METHODS = ("sgbm", "sweep")


@dataclass(frozen=True)
class MapperStageConfig:
    """The live mapper (``mapping`` in the run config)."""

    enabled: bool = False
    """Dense mapping during `slam run` (also `slam run --mesh`)."""
    voxel_m: float = bounded(0.02, gt=0)
    """TSDF voxel size, metres."""
    # bounds: above the plane sweep's nearest plane (0.4 m, the mapper stage's _make_mapper)
    max_depth_m: float = bounded(4.0, gt=0.4)
    """Depths beyond this are not fused."""
    depth_method: str = "sgbm"
    """Stereo depth per keyframe: "sgbm" (semi-global matching on the rectified pair, ~4x
    cheaper than the sweep at full size) or "sweep" (plane sweep over the pair and the
    previous keyframe)."""
    depth_scale: float = bounded(1.0, gt=0, le=1)
    """Depth at this fraction of the image size (0.5 is ~3-4x cheaper, but coarser)."""
    num_planes: int = bounded(96, ge=2)
    """Plane-sweep depth hypotheses (inverse-depth sampled; ``depth_method: sweep``)."""
    sweep_threads: int = bounded(1, ge=1)
    """Threads of the worker's depth (plane sweep strips; SGBM: OpenCV's pool) and fusion
    (numba); a background process (SCHED_IDLE, or nice +15: ``idle_worker``), so it
    yields to tracking. 1: the mapper needs ~0.3 of a core at ~3-4 keyframes/s, and a second
    thread only takes the front end's core in bursts (numba's workers spin when descheduled:
    TSDF 13 -> 34 ms CPU per depth map on 2 threads under load, BENCHMARKS.md "Mapping")."""
    idle_worker: bool = True
    """Run the mapper process's live work under Linux's SCHED_IDLE policy (its end-of-run
    catch-up and mesh stay at normal priority). A core that runs only SCHED_IDLE work counts
    as idle when a thread wakes, so the front end (and the player, reader and other workers)
    take it at once; at nice +15 the mapper kept its core for its slice and the front end
    queued behind (BENCHMARKS.md "Front end's p99 with the mapper"). While normal-priority
    work keeps both cores busy the mapper gets almost no CPU: its keyframes are dropped and
    the new views among them fused at the end (``catch_up_*``). False: nice +15 only
    (``player.idle_workers`` puts it under SCHED_IDLE too)."""
    pause_while_tracking: bool = True
    """Stop the mapper process (SIGSTOP, then SIGCONT) while the front end works on a frame,
    when the mapper has a keyframe in hand; paced playback only (``player.speed`` > 0: at
    ``max`` the front end never rests and the mapper would get nothing). SCHED_IDLE alone
    does not keep the mapper off the front end on 2 cores: a preempted front end waits on
    its core while the other runs the mapper, and the hypervisor sees no guest priority.
    Interleaved in one run (hall, ``--speed 1``, loaded machine): front-end latency p90 42 ms
    with the mapper working beside it, 25 ms with it stopped (BENCHMARKS.md, "Front end's
    p99 with the mapper: stopped during frames"). The mapper keeps the front end's idle time
    (~80 % of each frame interval at 20 Hz)."""
    max_backlog: int = bounded(4, ge=1)
    """Keyframes waiting for the mapper; beyond that a keyframe is dropped (and counted)."""
    catch_up_max_keyframes: int = bounded(300, ge=0)
    """Keyframes dropped while the mapper was behind are held (their images, ~0.7 MB per
    752x480 pair: up to ~220 MB) up to this many and fused at the end of the run, at their
    final poses (hall at --speed max: 150 -> 300 took completion 89.4 -> 94.8 %); 0:
    dropped for good. Only a keyframe that shows something new is held (see
    ``catch_up_min_distance_m``); when the hold is full, every other held keyframe is let go
    and from then on only every other new view is held, so the hold stays spread over the run."""
    catch_up_min_distance_m: float = bounded(0.10, ge=0)
    """A dropped keyframe is held only if it is this far from every keyframe sent or held..."""
    catch_up_min_angle_deg: float = bounded(8.0, ge=0)
    """...or rotated this much from it (else its view is mostly fused already)."""
    catch_up_s: float = bounded(60.0, ge=0)
    """End-of-run wall-time budget for fusing the held keyframes (spread over them: when it
    runs out, the ones left are evenly spaced in time, not the last stretch)."""
    mesh_every_s: float = bounded(5.0, ge=0)
    """Send a mesh snapshot to the viewer at most this often (marching cubes is not free)."""
    reintegrate_per_keyframe: int = bounded(2, ge=0, unit="keyframes")
    """During the run, after each keyframe re-integrate at most this many keyframes that a loop
    correction moved (spread out so the mapper keeps up); 0: only at the end."""
    final_reintegration: bool = True
    """At the end, re-integrate keyframes whose final (optimised, loop-closed) pose moved."""

    def __post_init__(self) -> None:
        if self.depth_method not in DEPTH_METHODS:
            raise SlamError(
                f"config key mapping.depth_method must be one of {', '.join(DEPTH_METHODS)}, "
                f"got {self.depth_method!r}"
            )

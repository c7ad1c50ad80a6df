"""Live rerun visualisation as a pipeline stage: it only reads snapshots, never estimator state.

Modes (``--rerun``): ``spawn`` (a viewer window), ``save:FILE.rrd``, ``serve`` (a web viewer
on this machine only; ``serve:HOST`` binds another address, e.g. ``serve:0.0.0.0`` to let
other machines watch), ``connect:URL`` (a running viewer, e.g.
rerun+http://127.0.0.1:9876/proxy) or ``none``.

The viewer never holds up a run: the stages hand it messages without waiting (it drops what it
cannot take), it logs in its own thread, and its end is bounded. A viewer that cannot start
costs one warning: without a display, ``spawn`` records to a file instead. ``serve`` starts
rerun's own server (``rerun --serve-web --bind``) as a separate process, so the final map can
still be looked at after the run (``--keep-viewer``). Images are JPEG-compressed
(FIELD_NOTES: ~2.4 ms and 60 kB per frame instead of 372 kB raw).

Time is one ``sequence_time`` timeline, a duration since the sequence's first frame, for every
sequence: stamps are epoch nanoseconds in EuRoC but start at 0 in synthetic sequences, which
rerun would show as 1970-01-01 if they were timestamps.
"""

from __future__ import annotations

import logging
import os
import shutil
import socket
import subprocess
import sys
import threading
import time
import urllib.parse
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from slam.config import VizConfig
from slam.core.calibration import Calibration
from slam.core.errors import SlamError
from slam.core.geometry import invert_transform
from slam.core.messages import (
    BackendOutput,
    Keyframe,
    LoopCorrection,
    MeshSnapshot,
    TrackingResult,
)
from slam.core.trajectory import Trajectory
from slam.runtime.stage import Stage

log = logging.getLogger(__name__)

RERUN_MODES = "spawn | save:FILE.rrd | serve[:HOST] | connect:URL | none"
TIMELINE = "sequence_time"
LOCALHOST = "127.0.0.1"


def _blueprint() -> Any:
    import rerun.blueprint as rrb

    return rrb.Blueprint(
        rrb.Horizontal(
            rrb.Spatial3DView(name="map", origin="world"),
            rrb.Vertical(
                rrb.Spatial2DView(name="camera", origin="world/body/cam0"),
                rrb.TimeSeriesView(name="front-end latency (ms)", origin="plots/latency"),
                rrb.TimeSeriesView(name="features", origin="plots/features"),
                rrb.TextLogView(name="events", origin="log"),
                row_shares=[3, 2, 2, 2],
            ),
            column_shares=[3, 2],
        ),
        # A live run: the view follows the newest data.
        rrb.TimePanel(state="collapsed", play_state="following", timeline=TIMELINE),
        collapse_panels=True,
    )


def has_display() -> bool:
    """Whether a viewer window can open here (Linux: an X11 or Wayland display is set)."""
    if not sys.platform.startswith("linux"):
        return True
    return bool(os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY"))


def _free_port(host: str) -> int:
    with socket.socket() as s:
        s.bind((host, 0))
        return int(s.getsockname()[1])


def _wait_for_port(host: str, port: int, proc: subprocess.Popen[bytes], timeout_s: float) -> bool:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline and proc.poll() is None:
        try:
            with socket.create_connection((host, port), timeout=0.2):
                return True
        except OSError:
            time.sleep(0.1)
    return False


@dataclass
class ViewerSession:
    """An open rerun recording and, for ``serve``, the server process it streams to."""

    rec: Any
    mode: str
    server: subprocess.Popen[bytes] | None = None
    web_url: str | None = None

    def close(self, timeout_s: float = 5.0) -> None:
        """Flush and disconnect, within ``timeout_s`` (in a daemon thread: a viewer that stopped
        reading must not keep the run from ending); the server keeps running until
        :meth:`stop_server`."""

        def end() -> None:
            try:
                self.rec.flush(timeout_sec=timeout_s)
                self.rec.disconnect()
            except Exception as exc:  # a viewer that went away must not fail the run
                log.warning("viewer: %s", exc)

        closer = threading.Thread(target=end, name="viewer-close", daemon=True)
        closer.start()
        closer.join(timeout_s + 1.0)
        if closer.is_alive():
            log.warning("viewer: did not take the end of the recording within %.0f s", timeout_s)

    def server_wait(self) -> None:
        """Block while the server runs (until Ctrl-C)."""
        if self.server is not None:
            self.server.wait()

    def stop_server(self) -> None:
        if self.server is not None and self.server.poll() is None:
            self.server.terminate()
            try:
                self.server.wait(timeout=5)
            except subprocess.TimeoutExpired:
                self.server.kill()


def _rerun_binary() -> str | None:
    """The rerun executable itself: the ``rerun`` script on PATH is a Python wrapper that
    starts it as a child, which terminating the wrapper would leave running."""
    try:
        import rerun_cli

        exe = Path(rerun_cli.__file__).parent / "rerun"
        if exe.is_file():
            return str(exe)
    except ImportError:
        pass
    return shutil.which("rerun", path=str(Path(sys.executable).parent)) or shutil.which("rerun")


def _serve(rec: Any, bp: Any, host: str) -> ViewerSession:
    """Start ``rerun --serve-web`` bound to ``host`` and stream the recording to it."""
    exe = _rerun_binary()
    if exe is None:
        raise SlamError("--rerun serve: the rerun command is not installed (pip install rerun-sdk)")
    grpc_port, web_port = _free_port(LOCALHOST), _free_port(LOCALHOST)
    cmd = [
        exe,
        "--serve-web",
        "--bind",
        host,
        "--port",
        str(grpc_port),
        "--web-viewer-port",
        str(web_port),
        "--server-memory-limit",
        "25%",
    ]
    server = subprocess.Popen(  # its own session: Ctrl-C in the run's terminal is ours to handle
        cmd,
        stdin=subprocess.DEVNULL,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
        start_new_session=True,
    )
    if not _wait_for_port(LOCALHOST, grpc_port, server, timeout_s=20.0):
        server.terminate()
        raise SlamError("--rerun serve: the rerun server did not start")
    url_host = LOCALHOST if host in ("0.0.0.0", "::", LOCALHOST) else host  # noqa: S104
    grpc_url = f"rerun+http://{url_host}:{grpc_port}/proxy"
    rec.connect_grpc(f"rerun+http://{LOCALHOST}:{grpc_port}/proxy", default_blueprint=bp)
    web = f"http://{url_host}:{web_port}/?url={urllib.parse.quote(grpc_url, safe='')}"
    return ViewerSession(rec, "serve", server, web)


def open_recording(
    mode: str, out_dir: Path | None = None, app_id: str = "pyvislam"
) -> ViewerSession | None:
    """The rerun session for a ``--rerun`` mode string, or None for ``none``.

    A viewer that cannot start is a warning, not an error: the run goes on without it (or,
    for ``spawn`` without a display, records to ``OUT/recording.rrd``).
    """
    if mode in ("", "none"):
        return None
    if not (mode in ("spawn", "serve") or mode.startswith(("save:", "serve:", "connect:"))):
        raise SlamError(f"unknown --rerun mode {mode!r}; use one of: {RERUN_MODES}")
    if mode.startswith("save:") and not mode[5:]:
        raise SlamError("--rerun save: needs a file name, e.g. --rerun save:run.rrd")
    import rerun as rr

    rec = rr.RecordingStream(app_id)
    bp = _blueprint()
    if mode == "spawn":
        if not has_display():
            if out_dir is None:
                log.warning("--rerun spawn: no display here (DISPLAY is not set); no viewer")
                return None
            path = Path(out_dir) / "recording.rrd"
            log.warning(
                "--rerun spawn: no display here (DISPLAY is not set); recording to %s instead "
                "(look at it with: rerun %s --web-viewer --bind 127.0.0.1; or use --rerun serve)",
                path,
                path,
            )
            rec.save(str(path), default_blueprint=bp)
            return ViewerSession(rec, f"save:{path}")
        try:
            rec.spawn(default_blueprint=bp)
        except Exception as exc:
            log.warning("--rerun spawn: the viewer did not start (%s); no viewer", exc)
            return None
        return ViewerSession(rec, mode)
    if mode.startswith("save:"):
        rec.save(mode[5:], default_blueprint=bp)
        return ViewerSession(rec, mode)
    if mode == "serve" or mode.startswith("serve:"):
        host = mode[6:] or LOCALHOST
        if host != LOCALHOST:
            log.warning(
                "--rerun %s: the viewer listens on %s: other machines that reach it can watch",
                mode,
                host,
            )
        return _serve(rec, bp, host)
    try:
        rec.connect_grpc(mode[8:], default_blueprint=bp)
    except Exception as exc:
        log.warning("--rerun %s: cannot connect (%s); no viewer", mode, exc)
        return None
    return ViewerSession(rec, mode)


class RerunStage(Stage):
    """Consumes TrackingResult / Keyframe / Estimate snapshots and logs them, at their time
    since ``origin_ns`` (the sequence's first frame) on the :data:`TIMELINE`."""

    def __init__(
        self,
        rec: Any,
        calib: Calibration,
        cfg: VizConfig,
        ground_truth: Trajectory | None,
        threaded: bool,
        origin_ns: int,
    ):
        super().__init__("viewer", maxsize=8, threaded=threaded)
        self.failed_logs = 0
        import rerun as rr

        self.rr = rr
        self.rec = rec
        self.cfg = cfg
        self.calib = calib
        self.ground_truth = ground_truth
        self.gt_logged = False
        self.seen_initialized = False
        self.positions: list[np.ndarray] = []
        self.kf_positions: list[np.ndarray] = []
        self.last_state = ""
        self.n_results = 0
        self.static_logged = False
        self.origin_ns = int(origin_ns)

    def _log_static(self) -> None:
        """The rig, once, from the viewer's own thread (a logging call may block; the stage's
        caller must never)."""
        self.static_logged = True
        rr, rec = self.rr, self.rec
        cam = self.calib.cameras[0]
        intr = cam.intrinsics
        rec.log("world", rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)
        rec.log(
            "world/body/cam0",
            rr.Transform3D(translation=cam.body_from_cam[:3, 3], mat3x3=cam.body_from_cam[:3, :3]),
            static=True,
        )
        rec.log(
            "world/body/cam0",
            rr.Pinhole(
                image_from_camera=intr.K,
                resolution=[intr.width, intr.height],
                image_plane_distance=0.3,
            ),
            static=True,
        )

    def _time(self, t_ns: int) -> None:
        self.rec.set_time(TIMELINE, duration=np.timedelta64(int(t_ns) - self.origin_ns, "ns"))

    def process(self, msg: Any) -> None:
        try:
            self._process(msg)
        except Exception as exc:  # a viewer problem never fails the run
            self.failed_logs += 1
            if self.failed_logs == 1:
                log.warning(
                    "viewer: logging failed (%s: %s); the run goes on", type(exc).__name__, exc
                )

    def _process(self, msg: Any) -> None:
        if not self.static_logged:
            self._log_static()
        if isinstance(msg, TrackingResult):
            self._log_result(msg)
        elif isinstance(msg, Keyframe):
            self._time(msg.t_ns)
            self.kf_positions.append(msg.world_from_body_vo[:3, 3].copy())
            rr = self.rr
            self.rec.log(
                "world/keyframes",
                rr.Points3D(np.array(self.kf_positions), colors=[255, 170, 0], radii=0.03),
            )
            if len(msg.points_world_vo):
                self.rec.log(
                    "world/landmarks/new",
                    rr.Points3D(msg.points_world_vo, colors=[120, 120, 255], radii=0.015),
                )
        elif isinstance(msg, MeshSnapshot):
            if msg.t_ns:
                self._time(msg.t_ns)
            self.rec.log(
                "world/mesh",
                self.rr.Mesh3D(
                    vertex_positions=msg.vertices_m,
                    triangle_indices=msg.faces,
                    vertex_normals=msg.normals,
                    vertex_colors=msg.colors_rgb,
                ),
                static=msg.t_ns == 0,
            )
        elif isinstance(msg, BackendOutput):
            est = msg.estimate
            if est is not None:
                self._time(est.t_ns)
            for text in msg.events:
                self.rec.log("log", self.rr.TextLog(text))
            if msg.mono_scale > 0:  # monocular: the start's scale estimates, tried and accepted
                self.rec.log("plots/mono_scale_m_per_vo_unit", self.rr.Scalars(msg.mono_scale))
            if est is None:
                return
            if est.time_offset is not None:
                off = est.time_offset
                self.rec.log(
                    "plots/time_offset_ms/estimate", self.rr.Scalars(off.estimate_ns * 1e-6)
                )
                self.rec.log("plots/time_offset_ms/applied", self.rr.Scalars(off.applied_ns * 1e-6))
            if len(est.landmark_positions_world):
                self.rec.log(
                    "world/landmarks/optimised",
                    self.rr.Points3D(est.landmark_positions_world, colors=[0, 200, 90], radii=0.02),
                )
        elif isinstance(msg, LoopCorrection):
            from slam.loop.viz import log_loop_correction

            self._time(msg.t_ns)
            self.rec.log(
                "log",
                self.rr.TextLog(
                    f"loop closed: keyframe {msg.query_keyframe_id} -> "
                    f"{msg.match_keyframe_id} ({msg.inliers} inliers)"
                ),
            )
            log_loop_correction(self.rec, msg, None)

    def _log_result(self, res: TrackingResult) -> None:
        rr = self.rr
        self._time(res.t_ns)
        self.n_results += 1
        if res.in_backend_world and not self.seen_initialized:
            # The front end moved into the back end's gravity-aligned world (results come in
            # order; an estimate may arrive before the first result in that world): start the
            # estimated path afresh and re-anchor the ground truth at this pose.
            self.seen_initialized = True
            self.positions = []
            self.gt_logged = False
        if res.state != self.last_state or res.reason:
            if res.state != self.last_state:
                level = "WARN" if res.state == "lost" else "INFO"
                text = f"{res.state}" + (f": {res.reason}" if res.reason else "")
                if res.state == "init":
                    text = f"map segment {res.segment_id} initialised from stereo"
                self.rec.log("log", rr.TextLog(text, level=level))
            self.last_state = res.state
        self.rec.log("plots/latency/frontend", rr.Scalars(res.latency_ms))
        self.rec.log("plots/features/tracked", rr.Scalars(float(res.num_tracked)))
        self.rec.log("plots/features/inliers", rr.Scalars(float(res.num_inliers)))
        if res.world_from_body is None:
            return
        # the live pose in the loop-corrected map (the odometry until a loop is closed)
        pose = res.map_from_body if res.map_from_body is not None else res.world_from_body
        if res.map_jump_m > 0 or res.map_jump_deg > 0:
            self.rec.log(
                "log",
                rr.TextLog(
                    f"live pose corrected: {res.map_jump_m * 100:.1f} cm, "
                    f"{res.map_jump_deg:.2f} deg"
                ),
            )
            self.rec.log("plots/live_correction_cm", rr.Scalars(res.map_jump_m * 100))
        self.rec.log("world/body", rr.Transform3D(translation=pose[:3, 3], mat3x3=pose[:3, :3]))
        self.positions.append(pose[:3, 3].copy())
        if self.n_results % 5 == 0 or res.is_keyframe:
            self.rec.log(
                "world/trajectory/estimate",
                rr.LineStrips3D([np.array(self.positions)], colors=[255, 60, 60], radii=0.01),
            )
        if self.ground_truth is not None and not self.gt_logged:
            self._log_ground_truth(res.t_ns, pose)
        if (
            res.image_left is not None
            and self.n_results % max(self.cfg.image_every_n_frames, 1) == 0
        ):
            ok, jpeg = cv2.imencode(
                ".jpg", res.image_left, [cv2.IMWRITE_JPEG_QUALITY, self.cfg.jpeg_quality]
            )
            if ok:
                self.rec.log(
                    "world/body/cam0/image",
                    rr.EncodedImage(contents=jpeg.tobytes(), media_type="image/jpeg"),
                )
        if len(res.feature_pixels):
            age = np.clip(res.feature_ages / 20.0, 0.0, 1.0)
            colors = np.stack([255 * (1 - age), 255 * age, np.full_like(age, 60)], axis=1).astype(
                np.uint8
            )
            old = res.feature_reobserved
            if old is not None and len(old) == len(colors):
                colors[old] = (60, 140, 255)  # landmarks found again in the map: blue
            self.rec.log(
                "world/body/cam0/image/features",
                rr.Points2D(res.feature_pixels, colors=colors, radii=2.0),
            )

    def _log_ground_truth(self, t_ns: int, est_pose: np.ndarray) -> None:
        """Show ground truth in the estimate's world frame, anchored at the first tracked pose."""
        gt = self.ground_truth
        assert gt is not None
        if len(gt) == 0 or t_ns < gt.t_ns[0] or t_ns > gt.t_ns[-1]:
            return
        i = int(np.clip(np.searchsorted(gt.t_ns, t_ns), 0, len(gt) - 1))
        gt_mats = gt.matrices()
        est_from_gt = est_pose @ invert_transform(gt_mats[i])
        pts = gt.positions_m @ est_from_gt[:3, :3].T + est_from_gt[:3, 3]
        self.rec.log(
            "world/trajectory/ground_truth",
            self.rr.LineStrips3D([pts], colors=[160, 160, 160], radii=0.006),
            static=True,
        )
        self.gt_logged = True

    def on_end(self) -> None:
        try:
            self.rec.log("log", self.rr.TextLog("end of sequence"))
        except Exception:  # noqa: S110 - the viewer may be gone; the run's end must not wait
            pass

"""The viewer never holds up a run: no display, a stuck viewer, and `serve` on localhost only."""

from __future__ import annotations

import os
import re
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any

import psutil
import pytest
from conftest import PROJECT_ROOT, synth_mcap, tracking_result

from slam.config import preset_config


@pytest.fixture(scope="module")
def seq_mcap(tmp_path_factory) -> Path:
    return synth_mcap(tmp_path_factory.mktemp("seq") / "seq.mcap", "figure8", 4)


def _slam_run(seq: Path, out: Path, *extra: str) -> list[str]:
    return [sys.executable, "-m", "tools.cli", "run", str(seq), "--out", str(out)] + [
        "--config",
        "stereo-vo",
        "--no-progress",
        *extra,
    ]


def test_spawn_without_a_display_records_to_a_file_and_ends(seq_mcap, tmp_path) -> None:
    env = {k: v for k, v in os.environ.items() if k not in ("DISPLAY", "WAYLAND_DISPLAY")}
    out = tmp_path / "run"
    t0 = time.monotonic()
    proc = subprocess.run(
        _slam_run(seq_mcap, out, "--rerun", "spawn", "--speed", "max"),
        cwd=PROJECT_ROOT,
        env=env,
        capture_output=True,
        text=True,
        timeout=180,
    )
    assert proc.returncode == 0, proc.stderr
    assert time.monotonic() - t0 < 120
    assert "no display" in proc.stderr
    assert (out / "recording.rrd").stat().st_size > 10_000
    assert (out / "trajectory.tum").exists()


def test_serve_listens_on_localhost_only_and_ends_with_the_run(seq_mcap, tmp_path) -> None:
    out = tmp_path / "run"
    proc = subprocess.Popen(
        _slam_run(seq_mcap, out, "--rerun", "serve", "--speed", "1"),
        cwd=PROJECT_ROOT,
        env=dict(os.environ, PYTHONUNBUFFERED="1"),
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    assert proc.stdout is not None
    url = ""
    for line in proc.stdout:
        if line.startswith("rerun web viewer:"):
            url = line.split(":", 1)[1].strip()
            break
    match = re.match(
        r"http://127\.0\.0\.1:(\d+)/\?url=rerun%2Bhttp%3A%2F%2F127\.0\.0\.1%3A(\d+)", url
    )
    assert match, url
    ports = {int(match.group(1)), int(match.group(2))}
    listening = [
        c
        for c in psutil.net_connections(kind="inet")
        if c.status == psutil.CONN_LISTEN and c.laddr.port in ports
    ]
    assert {c.laddr.port for c in listening} == ports
    assert all(c.laddr.ip == "127.0.0.1" for c in listening), listening
    _, err = proc.communicate(timeout=120)
    assert proc.returncode == 0, err
    time.sleep(0.5)
    still = [
        c
        for c in psutil.net_connections(kind="inet")
        if c.status == psutil.CONN_LISTEN and c.laddr.port in ports
    ]
    assert not still, "the viewer server outlived the run (no --keep-viewer)"


class _StuckRecording:
    """A recording whose every call blocks, like rr.log towards a viewer that never reads."""

    def __init__(self) -> None:
        self.release = threading.Event()

    def __getattr__(self, name: str) -> Any:
        def call(*args: Any, **kwargs: Any) -> None:
            self.release.wait(kwargs.get("timeout_sec"))  # rerun's flush honours its timeout

        return call


def test_a_stuck_viewer_does_not_hold_up_the_run(monkeypatch, tmp_path) -> None:
    from datasets.synth import make_synthetic_sequence
    from slam.runtime import wiring
    from slam.runtime.viewer import ViewerSession

    stuck = _StuckRecording()
    monkeypatch.setattr(wiring, "open_recording", lambda mode, out: ViewerSession(stuck, mode))
    seq = make_synthetic_sequence(profile="figure8", duration_s=2.0, seed=3)
    cfg = preset_config("stereo-vo")
    cfg.player.speed = 0.0
    t0 = time.monotonic()
    try:
        res = wiring.run_slam(seq, cfg, tmp_path, rerun_mode="spawn", progress=False)
    finally:
        stuck.release.set()
    assert res.stats["frames_tracked"] == seq.num_frames
    assert res.error is None
    assert time.monotonic() - t0 < 60


class _TimeLog:
    """A recording that keeps every ``set_time`` call and ignores the rest."""

    def __init__(self) -> None:
        self.times: list[tuple[str, dict[str, Any]]] = []

    def set_time(self, timeline: str, **kwargs: Any) -> None:
        self.times.append((timeline, kwargs))

    def __getattr__(self, name: str) -> Any:
        return lambda *args, **kwargs: None


def test_viewer_time_is_a_duration_since_the_first_frame() -> None:
    """Not a timestamp: synthetic stamps start at 0, which rerun would show as 1970-01-01."""
    import numpy as np

    from datasets.memory import random_sequence
    from slam.core.messages import LoopCorrection
    from slam.runtime import wiring
    from slam.runtime.viewer import TIMELINE, ViewerSession

    seq = random_sequence(num_frames=3)  # EuRoC-like epoch stamps
    t0 = int(seq.frame_times_ns()[0])
    assert t0 > 10**18
    rec = _TimeLog()
    cfg = preset_config("stereo-vo")
    cfg.player.sequential = True
    viewer = wiring.build(seq, cfg, ViewerSession(rec, "save:x.rrd")).viewer
    assert viewer is not None
    viewer.process(tracking_result(t0 + 2_400_000_000, np.eye(4), frame_index=48))
    viewer.process(LoopCorrection(t0 + 3_000_000_000, 0, 5, 1, 40, 1, {0: np.eye(4)}, {}))
    assert viewer.failed_logs == 0
    assert rec.times == [
        (TIMELINE, {"duration": np.timedelta64(2_400_000_000, "ns")}),
        (TIMELINE, {"duration": np.timedelta64(3_000_000_000, "ns")}),
    ]

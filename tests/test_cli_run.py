"""CLI smoke tests of `slam run`: every headless rerun mode, outputs, then `slam eval` on them."""

from __future__ import annotations

import json
import random
import subprocess
import sys
from pathlib import Path

import pytest
from conftest import PROJECT_ROOT, synth_mcap

from tools.cli import main as slam


@pytest.fixture(scope="module")
def seq_path(tmp_path_factory) -> Path:
    return synth_mcap(tmp_path_factory.mktemp("seq") / "fig8.mcap", "figure8", 4)


@pytest.mark.parametrize("preset", ["stereo-vo", "euroc-stereo-imu"])
@pytest.mark.parametrize("rerun_mode", ["none", "save"])
def test_run_outputs_and_eval(seq_path, tmp_path, rerun_mode, preset):
    out = tmp_path / "run"
    mode = f"save:{tmp_path / 'run.rrd'}" if rerun_mode == "save" else "none"
    argv = [
        "run",
        str(seq_path),
        "--out",
        str(out),
        "--speed",
        "max",
        "--rerun",
        mode,
        "--config",
        preset,
        "--no-progress",
    ]
    assert slam(argv) == 0
    for name in ("trajectory.tum", "trajectory.csv", "keyframes.tum", "stats.json", "config.yaml"):
        assert (out / name).stat().st_size > 0, name
    stats = json.loads((out / "stats.json").read_text())
    assert stats["frames_in"] == 81 and stats["frames_tracked"] == 81
    for key in ("p50_ms", "p90_ms", "p99_ms", "max_ms"):
        assert stats["latency"]["frontend_frame"][key] > 0
    assert stats["peak_rss_mb"] > 0
    if preset == "euroc-stereo-imu":
        assert stats["backend"]["initialised_after_s"] is not None
    if rerun_mode == "save":
        rrd = tmp_path / "run.rrd"
        assert rrd.stat().st_size > 10_000
        rerun_bin = Path(sys.executable).parent / "rerun"
        if rerun_bin.exists():
            proc = subprocess.run(
                [str(rerun_bin), "rrd", "verify", str(rrd)], capture_output=True, text=True
            )
            assert proc.returncode == 0, proc.stderr
    # `slam eval ape SEQ DIR` works directly on the outputs
    ape_json = tmp_path / "ape.json"
    assert (
        slam(["eval", "ape", str(seq_path), str(out), "--align", "se3", "--json", str(ape_json)])
        == 0
    )
    rmse = json.loads(ape_json.read_text())["stats"]["rmse"]
    assert rmse < 0.05


def test_run_bad_inputs_are_one_line_errors(tmp_path, capsys):
    assert slam(["run", str(tmp_path / "missing.mcap"), "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "error" in err[0]
    not_a_dir = tmp_path / "file.txt"
    not_a_dir.write_text("keep me\n")
    assert slam(["run", str(tmp_path / "missing.mcap"), "--out", str(not_a_dir)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "not a folder" in err[0]
    assert not_a_dir.read_text() == "keep me\n"
    cfg = tmp_path / "bad.yaml"
    cfg.write_text("frontend:\n  max_featurez: 10\n")
    seq = tmp_path / "s.mcap"
    assert slam(["synth", str(seq), "--duration", "1", "-q"]) == 0
    assert slam(["run", str(seq), "--out", str(tmp_path / "o"), "--config", str(cfg)]) == 2
    assert "max_featurez" in capsys.readouterr().err
    assert not (tmp_path / "o").exists()  # nothing made for a run that cannot start
    # a check of the config against the input, after loading: before --out is made, too
    late = tmp_path / "late.yaml"
    late.write_text("player:\n  sequential_estimate_delay_ms: 500\n")
    assert slam(["run", str(seq), "--out", str(tmp_path / "o"), "--config", str(late)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "sequential runs only" in err[0]
    assert not (tmp_path / "o").exists()


def test_an_input_that_cannot_be_opened_leaves_no_out_folder(tmp_path, capsys):
    noise = tmp_path / "noise.mcap"
    noise.write_bytes(random.Random(0).randbytes(4096))
    empty = tmp_path / "empty.mcap"
    empty.write_bytes(b"")
    for seq, why in (
        (noise, "not a sequence I can read"),
        (empty, "is empty (0 bytes)"),
        (tmp_path / "absent.mcap", "no such file or folder"),
    ):
        out = tmp_path / f"out_{seq.stem}" / "run"
        assert slam(["run", str(seq), "--out", str(out)]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and why in err[0]
        assert not out.parent.exists()


def test_strict_refuses_a_folder_with_a_missing_image(tmp_path, capsys):
    from test_euroc import write_asl_folder

    write_asl_folder(tmp_path / "seq")
    victim = sorted((tmp_path / "seq" / "mav0" / "cam0" / "data").iterdir())[2]
    victim.unlink()
    out = tmp_path / "out"
    assert slam(["run", str(tmp_path / "seq"), "--out", str(out), "--strict"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and f"image file missing: {victim}" in err[0] and "--strict" in err[0]
    assert not out.exists()


def test_help_teaches():
    proc = subprocess.run(
        [sys.executable, "-m", "tools.cli", "run", "--help"],
        capture_output=True,
        text=True,
        cwd=PROJECT_ROOT,
    )
    assert proc.returncode == 0
    assert (
        "examples:" in proc.stdout and "--rerun" in proc.stdout and "slam eval ape" in proc.stdout
    )
    # SEQ is described above its pointer, and the config keys' listing is named
    above, _, below = proc.stdout.partition("(see the description above)")
    assert below, "SEQ's help points to the description"
    assert "SEQ can be:\n  our MCAP file" in above
    assert "an EuRoC / TUM-VI folder" in above
    assert "every key with its default,\nunit and what it does: slam config show [PRESET]" in above


def test_run_with_mesh_writes_a_ply(seq_path, tmp_path):
    from datasets.ply import read_ply

    out = tmp_path / "run"
    argv = [
        "run",
        str(seq_path),
        "--out",
        str(out),
        "--speed",
        "max",
        "--mesh",
        "--config",
        "stereo-vo",
        "--no-progress",
    ]
    assert slam(argv) == 0
    stats = json.loads((out / "stats.json").read_text())
    assert stats["mapping"]["keyframes_fused"] >= 1
    ply = read_ply(out / "mesh.ply")
    assert len(ply.faces) > 1000
    v = ply.vertex
    # the room is 8 x 6 x 3 m: the mesh stays inside a box around it
    for axis in ("x", "y", "z"):
        assert abs(v[axis]).max() < 10.0


def test_memory_counts_the_whole_process_tree(seq_path, tmp_path):
    out = tmp_path / "run"
    argv = ["run", str(seq_path), "--out", str(out), "--speed", "max", "--no-progress"]
    assert slam(argv) == 0
    stats = json.loads((out / "stats.json").read_text())
    mem = stats["memory"]
    per = mem["per_process_peak_mb"]
    roles = {name.split(" (")[0] for name in per}
    assert {"main", "backend", "loop"} <= roles, per  # the stereo-inertial preset's workers
    if sys.platform == "linux":  # the reader names itself (/proc/PID/comm)
        assert "slam-reader" in roles, per
    assert mem["total_peak_mb"] >= max(per.values())
    assert mem["sum_of_process_peaks_mb"] >= mem["total_peak_mb"] - 1.0
    assert stats["peak_rss_mb"] == mem["total_peak_mb"]
    # one real-time factor: the tracking's, with the end-of-run work beside it
    assert stats["real_time_factor"] == pytest.approx(
        stats["sequence_duration_s"] / stats["tracking_wall_s"]
    )
    assert stats["end_of_run_s"] >= 0 and "loop" in stats["end_of_run_parts_s"]


def test_a_run_that_tracks_nothing_exits_non_zero(tmp_path):
    """Black frames: nothing can be tracked; the run ends with an error, not exit 0."""
    import numpy as np

    from datasets.mcap_io import write_sequence_mcap
    from datasets.memory import InMemorySequence, random_sequence

    textured = random_sequence(num_frames=12, width=160, height=120, seed=2)
    black = [np.zeros((120, 160), np.uint8)] * 12
    seq = InMemorySequence(
        "black",
        textured.calibration,
        textured.frame_times_ns(),
        black,
        black,
        textured.imu(),
        textured.ground_truth,
    )
    path = tmp_path / "black.mcap"
    write_sequence_mcap(seq, path, progress=False)
    proc = subprocess.run(
        [sys.executable, "-m", "tools.cli", "run", str(path), "--out", str(tmp_path / "run")]
        + ["--config", "stereo-vo", "--speed", "max", "--no-progress"],
        cwd=PROJECT_ROOT,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert proc.returncode == 1, proc.stderr
    assert "none of the 12 frames could be tracked" in proc.stderr
    assert "Traceback" not in proc.stderr


def test_a_worker_that_dies_is_an_error_of_its_own(seq_path, tmp_path):
    """The back-end worker is killed mid-run: exit 3, a message naming it, outputs kept."""
    import os
    import signal
    import time

    import psutil

    out = tmp_path / "run"
    cfg = tmp_path / "no-loop.yaml"
    cfg.write_text("preset: euroc-stereo-imu\nloop_closure: false\n")
    proc = subprocess.Popen(
        [sys.executable, "-m", "tools.cli", "run", str(seq_path), "--out", str(out)]
        + ["--config", str(cfg), "--speed", "0.5", "--no-progress"],
        cwd=PROJECT_ROOT,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    main = psutil.Process(proc.pid)
    deadline = time.monotonic() + 90
    workers: list[psutil.Process] = []
    while time.monotonic() < deadline and len(workers) < 2:  # the back end, then the reader
        workers = sorted(
            (c for c in main.children() if "spawn_main" in " ".join(c.cmdline())),
            key=lambda c: c.create_time(),
        )
        time.sleep(0.2)
    assert len(workers) >= 2, "the back-end worker and the reader did not start"
    time.sleep(1.0)
    os.kill(workers[0].pid, signal.SIGKILL)  # the first started: the back end
    _, err = proc.communicate(timeout=120)
    assert proc.returncode == 3, err
    assert "the backend worker process died (exit code -9)" in err
    assert "Traceback" not in err
    stats = json.loads((out / "stats.json").read_text())
    assert "backend" in stats["error"]
    assert (out / "trajectory.tum").exists()

"""`slam batch`: the task list, the engines' agreement, resumption after a kill, failed runs."""

from __future__ import annotations

import csv
import json
import os
import random
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from conftest import PROJECT_ROOT, synth_mcap

from slam.core.errors import SlamError
from tools.batch.report import REPORT_METRICS
from tools.batch.runner import run_batch
from tools.batch.spec import BatchSpec, ConfigChoice, build_tasks, expand_sequences, load_spec
from tools.cli import main as slam

#: Numbers that depend only on the run's output (not on timing): must agree between engines.
ACCURACY = ("ate_se3_m", "ate_posyaw_m", "ate_loop_closed_m", "rpe_1m_m", "drift_pct")
ACCURACY += ("completion_pct", "keyframes", "tracking_losses", "gt_path_m", "false_loops")


@pytest.fixture(scope="module")
def seqs(tmp_path_factory) -> dict[str, Path]:
    d = tmp_path_factory.mktemp("seqs")
    return {
        "fig8": synth_mcap(d / "fig8.mcap", "figure8", 3),
        "loop": synth_mcap(d / "loop.mcap", "loop", 2.5),
    }


def _spec(paths: list[Path], configs: list[ConfigChoice], repeats: int = 1) -> BatchSpec:
    spec = BatchSpec(expand_sequences([str(p) for p in paths], Path.cwd()), configs)
    spec.repeats, spec.sequential, spec.cpus_per_run = repeats, True, 2.0
    return spec


def _records(out: Path) -> dict[str, dict]:
    return {r["run_id"]: r for r in json.loads((out / "runs.json").read_text())["runs"]}


def test_tasks_are_built_in_one_place(tmp_path, seqs):
    spec_file = tmp_path / "batch.yaml"
    spec_file.write_text(
        f"sequences: ['{seqs['fig8'].parent}/*.mcap']\n"
        "configs:\n"
        "  - stereo-vo\n"
        "  - {name: few, base: euroc-stereo-imu, set: {frontend.max_features: 120}}\n"
        "repeats: 2\nsequential: true\n"
    )
    spec = load_spec(spec_file)
    tasks = build_tasks(spec)
    # repeat-major, then sequence, then configuration
    assert [t.run_id for t in tasks[:4]] == [
        "fig8/stereo-vo/rep1",
        "fig8/few/rep1",
        "loop/stereo-vo/rep1",
        "loop/few/rep1",
    ]
    assert len(tasks) == 8 and {t.repeat for t in tasks[4:]} == {2}
    few = tasks[1]
    assert few.config_arg is None and "max_features: 120" in (few.config_yaml or "")
    assert "preset: euroc-stereo-imu" in (few.config_yaml or "")
    assert tasks[0].config_arg == "stereo-vo" and tasks[0].config_yaml is None
    assert "--sequential" in tasks[0].run_args
    # same run, same fingerprint; another configuration, another one
    assert tasks[0].fingerprint == tasks[4].fingerprint != tasks[1].fingerprint
    # a bad key fails the batch before any run, in one line naming the configuration
    bad = _spec([seqs["fig8"]], [ConfigChoice("typo", "stereo-vo", {"frontend.max_featurez": 1})])
    with pytest.raises(SlamError, match=r"configuration 'typo': unknown config key .*max_features"):
        build_tasks(bad)
    with pytest.raises(SlamError, match="matches nothing"):
        expand_sequences([str(tmp_path / "*.nothing")], Path.cwd())


def test_local_and_ray_engines_give_the_same_runs(tmp_path, seqs, monkeypatch):
    configs = [
        ConfigChoice("stereo-vo", "stereo-vo"),
        ConfigChoice("vio", "euroc-stereo-imu"),
        ConfigChoice("no-loop", "euroc-stereo-imu", {"loop_closure": False}),
    ]
    spec = _spec([seqs["fig8"]], configs)
    local = run_batch(spec, tmp_path / "local", progress=False)
    assert (local.ran, local.failed, len(local.tasks)) == (3, 0, 3)
    runs = _records(tmp_path / "local")
    for r in runs.values():  # real runs, scored against the ground truth
        assert r["status"] == "ok" and r["metrics"]["completion_pct"] == 100.0
        assert r["metrics"]["ate_se3_m"] < 0.02
    no_loop = tmp_path / "local" / "runs" / "fig8" / "no-loop" / "rep1"
    assert "loop_closure: false" in (no_loop / "config.yaml").read_text()
    assert not (no_loop / "trajectory_loop_closed.tum").exists()
    for name in ("report.md", "report.csv", "runs.csv", "ate_boxplot.png", "trajectories.png"):
        assert (tmp_path / "local" / name).stat().st_size > 0, name

    ray = pytest.importorskip("ray", reason="Ray is optional: pip install '.[ray]'")
    import psutil
    from ray._private import ray_constants

    # Ray's local instance on the loopback interface only (its default is the machine's address)
    monkeypatch.setenv("RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER", "0")
    monkeypatch.setattr(ray_constants, "ENABLE_RAY_CLUSTER", False)
    ray.init(
        address="local",  # a new instance, even when this machine has a cluster running
        num_cpus=2,
        object_store_memory=200 * 1024**2,  # a run's files are small; /dev/shm may be too
        include_dashboard=False,
        log_to_driver=False,
        logging_level="ERROR",
    )
    try:
        listening = {
            c.laddr.ip
            for p in psutil.Process().children(recursive=True)
            for c in p.net_connections(kind="inet")
            if c.status == psutil.CONN_LISTEN
        }
        assert listening and listening <= {"127.0.0.1", "::ffff:127.0.0.1", "::1"}, listening
        remote = run_batch(spec, tmp_path / "ray", engine="ray", progress=False)
    finally:
        ray.shutdown()
    assert (remote.ran, remote.failed) == (3, 0)
    for run_id, r in _records(tmp_path / "ray").items():
        assert r["status"] == "ok"
        assert {k: r["metrics"].get(k) for k in ACCURACY} == {
            k: runs[run_id]["metrics"].get(k) for k in ACCURACY
        }, run_id
        for name in ("trajectory.tum", "keyframes.tum", "config.yaml", "eval/ape_se3.json"):
            a = (tmp_path / "local" / "runs" / run_id / name).read_bytes()
            assert a == (tmp_path / "ray" / "runs" / run_id / name).read_bytes(), (run_id, name)


def _accuracy_table(out: Path) -> list[dict[str, str]]:
    keep = ("sequence", "configuration", "runs", "runs_ok")
    rows = list(csv.DictReader((out / "report.csv").open()))
    acc = [k for k in REPORT_METRICS if k in ACCURACY]
    return [{k: v for k, v in r.items() if k in keep or k.rsplit("_", 1)[0] in acc} for r in rows]


def test_a_killed_batch_resumes_and_finishes_with_the_same_table(tmp_path, seqs):
    argv = [str(seqs["loop"]), "--config", "stereo-vo", "--repeats", "3", "--sequential"]
    reference = tmp_path / "reference"
    assert slam(["batch", *argv, "--out", str(reference), "--no-progress"]) == 0

    out = tmp_path / "killed"
    env = {**os.environ, "PYTHONPATH": str(PROJECT_ROOT)}
    cmd = [sys.executable, "-m", "tools.cli", "batch", *argv, "--out", str(out), "--no-progress"]
    proc = subprocess.Popen(cmd, env=env, start_new_session=True, stdout=subprocess.DEVNULL)
    first = out / "runs" / "loop" / "stereo-vo" / "rep1" / "run.json"
    deadline = time.monotonic() + 120
    while not first.exists() and proc.poll() is None and time.monotonic() < deadline:
        time.sleep(0.05)
    os.killpg(proc.pid, signal.SIGKILL)  # the batch and its slam run, as a machine would
    proc.wait()
    done_before = sorted(p.parent.name for p in out.glob("runs/*/*/*/run.json"))
    assert "rep1" in done_before and len(done_before) < 3, done_before
    record_before = first.read_bytes()

    resumed = run_batch(
        _spec([seqs["loop"]], [ConfigChoice("stereo-vo", "stereo-vo")], repeats=3),
        out,
        progress=False,
    )
    assert resumed.skipped == len(done_before) and resumed.ran == 3 - len(done_before)
    assert first.read_bytes() == record_before  # a finished run is not run again
    assert not (out / ".scratch").exists()
    assert _accuracy_table(out) == _accuracy_table(reference)
    assert _accuracy_table(out)[0]["runs_ok"] == "3"


def test_a_failing_run_is_recorded_and_the_others_finish(tmp_path, seqs, capsys):
    corrupt = tmp_path / "corrupt.mcap"
    corrupt.write_bytes(random.Random(0).randbytes(4096))
    out = tmp_path / "out"
    argv = ["batch", str(corrupt), str(seqs["fig8"]), "--config", "stereo-vo", "--sequential"]
    assert slam([*argv, "--out", str(out), "--no-progress"]) == 1  # a run failed
    runs = _records(out)
    bad, good = runs["corrupt/stereo-vo/rep1"], runs["fig8/stereo-vo/rep1"]
    assert bad["status"] == "failed" and "not a sequence I can read" in bad["error"]
    assert "\n" not in bad["error"]
    assert good["status"] == "ok" and good["metrics"]["ate_se3_m"] < 0.02
    report = (out / "report.md").read_text()
    assert "| corrupt | stereo-vo | 0/1 |" in report and "`corrupt/stereo-vo/rep1`" in report
    assert (out / "runs" / "corrupt" / "stereo-vo" / "rep1" / "slam_run.log").exists()


def test_ray_engine_without_ray_is_a_one_line_error(tmp_path, seqs, monkeypatch, capsys):
    monkeypatch.setitem(sys.modules, "ray", None)  # import ray -> ImportError
    argv = ["batch", str(seqs["fig8"]), "--engine", "ray", "--out", str(tmp_path / "o")]
    assert slam([*argv, "--no-progress"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "pip install '.[ray]'" in err[0]


def test_bad_spec_is_a_one_line_error(tmp_path, capsys):
    spec = tmp_path / "b.yaml"
    spec.write_text("sequences: [x.mcap]\nrepeat: 3\n")
    assert slam(["batch", "--spec", str(spec), "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "unknown key 'repeat'" in err[0]
    assert not (tmp_path / "o").exists()

"""`make demo` names only what it wrote (the mesh included) and says how to look at the
recording without a display."""

from __future__ import annotations

from pathlib import Path

import pytest

from tools import demo


def _fake_slam(calls: list[list[str]], mesh: bytes = b"ply\n"):  # type: ignore[no-untyped-def]
    """A `slam` that writes what each demo step's real command would (a stand-in, fast)."""

    def slam(argv: list[str]) -> int:
        calls.append(argv)
        if argv[0] == "synth":
            Path(argv[1]).write_bytes(b"mcap")
        elif argv[0] == "run":
            out = Path(argv[argv.index("--out") + 1])
            out.mkdir(parents=True, exist_ok=True)
            (out / "trajectory.tum").write_text("0 0 0 0 0 0 0 1\n")
            (out / "trajectory_loop_closed.tum").write_text("0 0 0 0 0 0 0 1\n")
            if "--mesh" in argv:
                (out / "mesh.ply").write_bytes(mesh)
            Path(argv[argv.index("--rerun") + 1].removeprefix("save:")).write_bytes(b"rrd")
        elif argv[0] == "eval":
            Path(argv[argv.index("--plot") + 1]).write_bytes(b"png")
        return 0

    return slam


def test_the_demo_writes_the_mesh_it_names(tmp_path: Path, monkeypatch, capsys) -> None:
    calls: list[list[str]] = []
    monkeypatch.setattr(demo, "slam_main", _fake_slam(calls))
    monkeypatch.setattr(demo, "_has_display", lambda: False)
    monkeypatch.setattr(demo, "rerun_command", lambda: ".venv/bin/rerun")
    out = tmp_path / "d"
    assert demo.main(["--out", str(out)]) == 0
    run = next(argv for argv in calls if argv[0] == "run")
    assert "--mesh" in run
    text = capsys.readouterr().out
    assert text.endswith(
        f"\nDone. Trajectory: {out}/run/trajectory.tum (loop-closed: "
        f"trajectory_loop_closed.tum); dense mesh: {out}/run/mesh.ply (MeshLab, Open3D); "
        f"error plot: {out}/ape.png.\n"
        f"Look at the recording: `.venv/bin/rerun {out}/run.rrd --web-viewer --bind 127.0.0.1` "
        "serves it on this machine only and prints a http://127.0.0.1:... address to open in a "
        "browser (Ctrl-C ends it).\n"
    )


def test_with_a_display_the_window_comes_first(tmp_path: Path) -> None:
    outputs = {
        k: tmp_path / n
        for k, n in [
            ("trajectory", "t.tum"),
            ("loop_closed", "l.tum"),
            ("mesh", "m.ply"),
            ("plot", "a.png"),
            ("recording", "r.rrd"),
        ]
    }
    text = demo.summary(outputs, "rerun", display=True)
    assert f"Look at the recording: `rerun {tmp_path}/r.rrd` opens it in a window; " in text
    assert f"without a display, `rerun {tmp_path}/r.rrd --web-viewer --bind 127.0.0.1`" in text


@pytest.mark.parametrize("mesh", [b"", None])
def test_a_missing_or_empty_output_fails_the_demo(
    tmp_path: Path, monkeypatch, capsys, mesh: bytes | None
) -> None:
    calls: list[list[str]] = []
    fake = _fake_slam(calls, mesh or b"")
    if mesh is None:  # the run step does not write the mesh at all

        def fake_without_mesh(argv: list[str]) -> int:
            return fake([a for a in argv if a != "--mesh"])

        monkeypatch.setattr(demo, "slam_main", fake_without_mesh)
    else:
        monkeypatch.setattr(demo, "slam_main", fake)
    out = tmp_path / "d"
    assert demo.main(["--out", str(out)]) == 1
    captured = capsys.readouterr()
    assert captured.err == f"demo: not written (or empty): {out}/run/mesh.ply\n"
    assert "Done." not in captured.out


def test_rerun_is_named_relative_to_the_current_folder(tmp_path: Path, monkeypatch) -> None:
    bin_dir = tmp_path / ".venv" / "bin"
    bin_dir.mkdir(parents=True)
    exe = bin_dir / "rerun"
    exe.write_text("#!/bin/sh\n")
    exe.chmod(0o755)
    monkeypatch.setattr(demo.sys, "executable", str(bin_dir / "python"))
    monkeypatch.chdir(tmp_path)
    assert demo.rerun_command() == ".venv/bin/rerun"

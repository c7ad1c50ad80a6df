"""tools.bench_ab: the A/B order, the table's medians and ratios, the exported versions."""

from __future__ import annotations

import shutil
import subprocess
from pathlib import Path

import pytest

from slam.core.errors import SlamError
from tools.bench_ab import REPO, markdown, run_order, source_tree


def test_each_version_runs_first_as_often_as_second() -> None:
    order = run_order(4)
    assert order == [(0, "a"), (0, "b"), (1, "b"), (1, "a"), (2, "a"), (2, "b"), (3, "b"), (3, "a")]
    firsts = [order[k][1] for k in range(0, len(order), 2)]
    assert firsts.count("a") == firsts.count("b") == 2


def test_table_gives_medians_and_b_over_a() -> None:
    def rec(v: str, rtf: float, p99: float | None) -> dict[str, object]:
        return {"sequence": "hall", "version": v, "real_time_factor": rtf, "frontend_p99_ms": p99}

    records = [rec("a", 2.0, 30.0), rec("b", 3.0, 20.0), rec("b", 2.0, None), rec("a", 4.0, 26.0)]
    records += [rec("a", 3.0, 28.0), rec("b", 4.0, 22.0)]
    table = markdown(records, {"a": "old", "b": "new"})
    rtf = next(line for line in table.splitlines() if "| RTF |" in line)
    assert rtf.split("|")[3:8] == [
        " 2.00 / 4.00 / 3.00 ",
        " 3.00 / 2.00 / 4.00 ",
        " 3.00 ",
        " 3.00 ",
        " 1.00 ",
    ]
    p99 = next(line for line in table.splitlines() if "| FE p99 ms |" in line)
    # B's median over the runs that have the figure: (20 + 22) / 2; A's 28
    assert p99.split("|")[5:8] == [" 28.0 ", " 21.0 ", " 0.75 "]
    steal = next(line for line in table.splitlines() if "| steal % |" in line)
    assert steal.split("|")[5:8] == [" - ", " - ", " - "]


@pytest.mark.skipif(
    shutil.which("git") is None or not (REPO / ".git").exists(), reason="needs the git checkout"
)
def test_a_commit_is_exported_with_its_tracked_files(tmp_path: Path) -> None:
    tree = source_tree("HEAD", tmp_path, "a")
    assert tree == (tmp_path / "tree-a").resolve()
    head = subprocess.run(
        ["git", "-C", str(REPO), "show", "HEAD:tools/cli.py"], capture_output=True, check=True
    ).stdout
    assert (tree / "tools" / "cli.py").read_bytes() == head
    assert not (tree / ".venv").exists()


def test_a_folder_is_used_as_it_is_and_nonsense_is_refused(tmp_path: Path) -> None:
    assert source_tree(str(REPO), tmp_path, "b") == REPO
    with pytest.raises(SlamError, match="neither a folder nor a git commit"):
        source_tree("no-such-commit-4f1c", tmp_path, "a")
    (tmp_path / "empty").mkdir()
    with pytest.raises(SlamError, match="not a source tree"):
        source_tree(str(tmp_path / "empty"), tmp_path, "b")

"""`slam eval` help and tables: each subcommand explains itself; a table says which metric and
which alignment each row is."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from slam.evaluation.results import EvalResult, format_table, load_rows, write_json
from tools.cli import main


def _help(capsys, *argv: str) -> str:
    with pytest.raises(SystemExit) as done:
        main(["eval", *argv, "--help"])
    assert done.value.code == 0
    return capsys.readouterr().out


def test_each_subcommand_has_its_own_help_with_examples(capsys) -> None:
    parent = _help(capsys)
    pages = {cmd: _help(capsys, cmd) for cmd in ("ape", "rpe", "table")}
    assert pages["ape"].split("\n\n")[1].startswith("Absolute pose error, as evo_ape")
    assert pages["rpe"].split("\n\n")[1].startswith("Relative pose error, as evo_rpe")
    assert pages["table"].split("\n\n")[1].startswith("One table of several results")
    for cmd, page in pages.items():
        assert "table  gather result files" not in page  # not the parent's text again
        examples = page.split("\nExamples:\n")[1].rstrip().splitlines()
        assert examples and all(ln.startswith(f"  slam eval {cmd} ") for ln in examples)
    assert "table  gather result files" in parent
    fmt = pages["table"].split("--format {markdown,csv,latex}\n")[1].splitlines()[0]
    assert fmt.strip() == "table format (default markdown)"


def _result(kind: str, relation: str, unit: str, method: str, n_used: int, **kw) -> EvalResult:
    errors = np.array([1.0, 2.0, 3.0])
    stats = {"rmse": 2.160247, "mean": 2.0, "median": 2.0, "std": 0.816497, "min": 1.0, "max": 3.0}
    return EvalResult(
        kind,
        "title",
        "gt.txt",
        "runs/run1",
        relation,
        unit,
        stats,
        errors,
        np.arange(3.0),
        alignment={"method": method, "n_used": n_used},
        association={"pairs": 3},
        **kw,
    )


def test_table_names_metric_and_alignment_of_each_row(tmp_path: Path) -> None:
    ape = tmp_path / "ape.json"
    write_json(ape, [_result("ape", "trans", "m", "posyaw", 3)])
    rpe = tmp_path / "rpe.json"
    write_json(
        rpe,
        [
            _result("rpe", "angle_deg", "deg", "none", 0, delta=1.0, delta_unit="metres"),
            _result("segments", "drift_pct", "%", "se3", 2, delta=100.0, delta_unit="metres"),
        ],
    )
    rows = load_rows(ape) + load_rows(rpe)
    assert format_table(rows, "csv", 2).splitlines() == [
        "run,metric,alignment,rmse,mean,median,std,min,max",
        "run1,APE trans (m),posyaw,2.16,2.00,2.00,0.82,1.00,3.00",
        'run1,"RPE angle_deg (deg), delta 1 m",none,2.16,2.00,2.00,0.82,1.00,3.00',
        'run1,"drift (%), 100 m",se3 (first 2),2.16,2.00,2.00,0.82,1.00,3.00',
    ]
    markdown = format_table(rows, "markdown", 2).splitlines()
    assert markdown[0].startswith(
        "| run  | metric                         | alignment     | rmse |"
    )
    assert markdown[1].startswith(
        "|------|--------------------------------|---------------|-----:|"
    )
    latex = format_table(rows, "latex", 2).splitlines()
    assert latex[0] == r"\begin{tabular}{lllrrrrrr}"
    assert (
        latex[6]
        == r"run1 & drift (\%), 100 m & se3 (first 2) & 2.16 & 2.00 & 2.00 & 0.82 & 1.00 & 3.00 \\"
    )


def test_evo_result_zips_get_the_same_metric_and_alignment_names(shared_data: Path) -> None:
    from conftest import require

    res = require(shared_data / "trajectories" / "evo_testdata" / "res_files")
    ape, rpe = load_rows(res / "orb_ape.zip")[0], load_rows(res / "orb_rpe.zip")[0]
    assert (ape.label, ape.metric, ape.alignment) == ("KITTI_00_ORB", "APE trans (m)", "se3")
    assert (rpe.metric, rpe.alignment) == ("RPE trans (m), delta 10 m", "none")

"""Evaluation results: one object per metric run, saved as JSON, gathered into tables.

``slam eval table`` reads our JSON files (one result or a list) and evo's result zips
(``stats.json`` + ``info.json``), and prints markdown, CSV or LaTeX.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from slam.core.errors import InputError

TABLE_FORMATS = ("markdown", "csv", "latex")
TABLE_COLUMNS = ("rmse", "mean", "median", "std", "min", "max")


@dataclass(eq=False)
class EvalResult:
    """One metric over one estimate: statistics, the error array and how it was obtained."""

    kind: str  # "ape", "rpe" or "segments"
    title: str
    reference: str
    estimate: str
    relation: str
    unit: str
    stats: dict[str, float]
    errors: np.ndarray
    t_s: np.ndarray  # seconds from the first associated estimate pose, one per error
    alignment: dict[str, Any] = field(default_factory=dict)
    association: dict[str, Any] = field(default_factory=dict)
    delta: float | None = None
    delta_unit: str | None = None
    all_pairs: bool = False
    extra: dict[str, Any] = field(default_factory=dict)

    def summary(self) -> str:
        """Console lines: title, then the statistics."""
        unit = f" {self.unit}" if self.unit else ""
        lines = [self.title, f"  pairs   {len(self.errors)}"]
        for key in ("rmse", "mean", "median", "std", "min", "max", "sse"):
            lines.append(f"  {key:<7} {self.stats[key]:.6g}{unit if key != 'sse' else ''}")
        return "\n".join(lines)

    def to_dict(self) -> dict[str, Any]:
        d = asdict(self)
        d["errors"] = self.errors.tolist()
        d["t_s"] = self.t_s.tolist()
        d["tool"] = "slam eval"
        return d

    @staticmethod
    def from_dict(d: dict[str, Any]) -> EvalResult:
        d = {k: v for k, v in d.items() if k != "tool"}
        d["errors"] = np.asarray(d.get("errors", []), dtype=float)
        d["t_s"] = np.asarray(d.get("t_s", []), dtype=float)
        return EvalResult(**d)


def write_json(path: str | Path, results: list[EvalResult]) -> None:
    """Write one result (a JSON object) or several (a list), atomically."""
    import json

    from slam.core.atomic import atomic_output

    payload: Any = results[0].to_dict() if len(results) == 1 else [r.to_dict() for r in results]
    with atomic_output(path, text=True) as f:
        json.dump(payload, f, indent=1)


@dataclass(frozen=True)
class TableRow:
    """A row of a results table: a label and statistics."""

    label: str
    title: str
    stats: dict[str, float]


def load_rows(path: str | Path) -> list[TableRow]:
    """Rows from our JSON result file or an evo result zip."""
    import json
    import zipfile

    p = Path(path)
    if not p.is_file():
        raise InputError(f"{p}: no such result file")
    if zipfile.is_zipfile(p):
        try:
            with zipfile.ZipFile(p) as z:
                info = json.loads(z.read("info.json"))
                stats = json.loads(z.read("stats.json"))
        except (KeyError, json.JSONDecodeError) as exc:
            raise InputError(f"{p}: not an evo result zip ({exc})") from None
        label = Path(str(info.get("est_name", p.stem))).stem
        return [TableRow(label, str(info.get("title", "")).replace("\n", " "), stats)]
    try:
        data = json.loads(p.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise InputError(f"{p}: not a JSON result file ({exc})") from None
    items = data if isinstance(data, list) else [data]
    rows = []
    for item in items:
        if not isinstance(item, dict) or "stats" not in item:
            raise InputError(f"{p}: not a `slam eval` result (no 'stats')")
        label = Path(str(item.get("estimate", p.stem))).name or p.stem
        if item.get("delta") is not None:
            label += f" (delta {item['delta']:g} {item.get('delta_unit', '')})"
        rows.append(TableRow(label, str(item.get("title", "")).replace("\n", " "), item["stats"]))
    return rows


def format_table(rows: list[TableRow], fmt: str = "markdown", digits: int = 4) -> str:
    """A table of statistics, one row per result."""
    if fmt not in TABLE_FORMATS:
        raise InputError(f"unknown table format {fmt!r}; choose one of {', '.join(TABLE_FORMATS)}")
    header = ["run", *TABLE_COLUMNS]
    body = [
        [r.label, *(f"{float(r.stats.get(c, float('nan'))):.{digits}f}" for c in TABLE_COLUMNS)]
        for r in rows
    ]
    if fmt == "csv":

        def esc(s: str) -> str:
            return f'"{s}"' if ("," in s or '"' in s) else s

        return "\n".join(",".join(esc(c) for c in line) for line in [header, *body]) + "\n"
    if fmt == "latex":

        def tex(s: str) -> str:
            for a, b in (
                ("\\", r"\textbackslash{}"),
                ("_", r"\_"),
                ("%", r"\%"),
                ("&", r"\&"),
                ("#", r"\#"),
            ):
                s = s.replace(a, b)
            return s

        lines = [
            r"\begin{tabular}{l" + "r" * len(TABLE_COLUMNS) + "}",
            r"\hline",
            " & ".join(header) + r" \\",
            r"\hline",
            *(" & ".join([tex(line[0]), *line[1:]]) + r" \\" for line in body),
            r"\hline",
            r"\end{tabular}",
        ]
        return "\n".join(lines) + "\n"
    widths = [max(len(line[k]) for line in [header, *body]) for k in range(len(header))]

    def row(cells: list[str]) -> str:
        return (
            "| "
            + " | ".join(
                c.ljust(w) if k == 0 else c.rjust(w) for k, (c, w) in enumerate(zip(cells, widths))
            )
            + " |"
        )

    sep = (
        "|"
        + "|".join(("-" * (w + 1) + ":") if k else ("-" * (w + 2)) for k, w in enumerate(widths))
        + "|"
    )
    return "\n".join([row(header), sep, *(row(b) for b in body)]) + "\n"

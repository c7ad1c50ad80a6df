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
from slam.evaluation.metrics import RELATION_TITLES

TABLE_FORMATS = ("markdown", "csv", "latex")
TABLE_COLUMNS = ("rmse", "mean", "median", "std", "min", "max")
#: The columns before the statistics: the estimate, what was measured, how it was aligned.
TABLE_TEXT_COLUMNS = ("run", "metric", "alignment")


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
    """A row of a results table: the run, what was measured, how it was aligned, statistics."""

    label: str
    title: str
    stats: dict[str, float]
    metric: str = ""
    alignment: str = ""


#: evo's words for an error relation -> ours (the ``--relation`` names).
_RELATION_NAMES = {title: name for name, title in RELATION_TITLES.items()}
#: A phrase of an evo title's last line -> our ``--align`` name.
_EVO_ALIGNMENTS = (
    ("SE(3)", "se3"),
    ("Sim(3)", "sim3"),
    ("scale corrected", "scale"),
    ("origin", "origin"),
    ("not aligned", "none"),
)
_DELTA_UNITS = {"metres": "m", "seconds": "s", "frames": "frames", "f": "frames"}


def metric_name(kind: str, relation: str, unit: str, delta: float | None, delta_unit: str) -> str:
    """Short name of a metric for tables: ``APE trans (m)``, ``RPE trans (m), delta 1 frames``,
    ``drift (%), 100 m``."""
    if kind == "segments":
        return f"drift ({unit}), {delta:g} m"
    text = f"{kind.upper()} {relation}" + (f" ({unit})" if unit else "")
    if delta is not None:
        text += f", delta {delta:g} {_DELTA_UNITS.get(delta_unit, delta_unit)}"
    return text


def alignment_name(alignment: dict[str, Any], pairs: int | None) -> str:
    """``se3``, ``posyaw``, ..., ``none``; ``se3 (first 50)`` when fitted on the first poses."""
    method = str(alignment.get("method", ""))
    n = alignment.get("n_used")
    if method in ("se3", "sim3", "scale", "posyaw") and pairs and n and n != pairs:
        return f"{method} (first {n})"
    return method


def _evo_title(title: str) -> tuple[str, str]:
    """(metric, alignment) from an evo result title such as
    ``APE w.r.t. translation part (m)\n(with SE(3) Umeyama alignment)``."""
    import re

    lines = [ln.strip() for ln in title.splitlines() if ln.strip()]
    alignment = ""
    if lines and lines[-1].startswith("("):
        last = lines.pop()
        alignment = next((ours for words, ours in _EVO_ALIGNMENTS if words in last), last[1:-1])
    head = re.fullmatch(r"(APE|RPE) w\.r\.t\. (.+?)(?: \((\w+)\))?", lines[0]) if lines else None
    delta = (
        re.fullmatch(r"for delta = ([-\d.e+]+) \((\w+)\).*", lines[1]) if len(lines) > 1 else None
    )
    if head and head.group(2) in _RELATION_NAMES and (len(lines) == 1 or delta):
        return (
            metric_name(
                head.group(1).lower(),
                _RELATION_NAMES[head.group(2)],
                head.group(3) or "",
                float(delta.group(1)) if delta else None,
                delta.group(2) if delta else "",
            ),
            alignment,
        )
    return ", ".join(ln.replace("w.r.t. ", "") for ln in lines), alignment


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
        title = str(info.get("title", ""))
        metric, alignment = _evo_title(title)
        return [TableRow(label, title.replace("\n", " "), stats, metric, alignment)]
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
        metric = metric_name(
            str(item.get("kind", "")),
            str(item.get("relation", "")),
            str(item.get("unit", "")),
            item.get("delta"),
            str(item.get("delta_unit") or ""),
        )
        alignment = alignment_name(
            item.get("alignment") or {}, (item.get("association") or {}).get("pairs")
        )
        title = str(item.get("title", "")).replace("\n", " ")
        rows.append(TableRow(label, title, item["stats"], metric, alignment))
    return rows


def format_table(rows: list[TableRow], fmt: str = "markdown", digits: int = 4) -> str:
    """A table of statistics, one row per result."""
    if fmt not in TABLE_FORMATS:
        raise InputError(f"unknown table format {fmt!r}; choose one of {', '.join(TABLE_FORMATS)}")
    header = [*TABLE_TEXT_COLUMNS, *TABLE_COLUMNS]
    n_text = len(TABLE_TEXT_COLUMNS)
    body = [
        [
            r.label,
            r.metric,
            r.alignment,
            *(f"{float(r.stats.get(c, float('nan'))):.{digits}f}" for c in TABLE_COLUMNS),
        ]
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
            r"\begin{tabular}{" + "l" * n_text + "r" * len(TABLE_COLUMNS) + "}",
            r"\hline",
            " & ".join(header) + r" \\",
            r"\hline",
            *(" & ".join([*map(tex, line[:n_text]), *line[n_text:]]) + r" \\" for line in body),
            r"\hline",
            r"\end{tabular}",
        ]
        return "\n".join(lines) + "\n"
    widths = [max(len(line[k]) for line in [header, *body]) for k in range(len(header))]

    def row(cells: list[str]) -> str:
        return (
            "| "
            + " | ".join(
                c.ljust(w) if k < n_text else c.rjust(w)
                for k, (c, w) in enumerate(zip(cells, widths))
            )
            + " |"
        )

    sep = (
        "|"
        + "|".join(
            ("-" * (w + 1) + ":") if k >= n_text else ("-" * (w + 2)) for k, w in enumerate(widths)
        )
        + "|"
    )
    return "\n".join([row(header), sep, *(row(b) for b in body)]) + "\n"

"""Plots of evaluation results (matplotlib, Agg backend; PNG or PDF by the file suffix).

APE: top view of the aligned estimate coloured by error, the reference dashed on top of it, and
the error over time with its rmse, mean and median (distinct colours and styles).
RPE: error over time per delta and box plots per delta. Segments: drift box plots per length.
The subtitle names the estimate and the reference (a bag with its topic).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from slam.evaluation.results import EvalResult


def display_name(name: str) -> str:
    """A file or folder's base name for a plot; a bag keeps its topic: ``room.mcap /gt/pose``."""
    file, sep, topic = name.partition(":/")
    if sep:
        return f"{Path(file).name} /{topic}"
    return Path(name).name or name


def joint_title(results: list[EvalResult]) -> str:
    """The title of one figure of several deltas or lengths: their values listed in place of
    the first one's (``... for delta = 1, 10 metres ...``, ``... over 2, 5, 10 m ...``)."""
    first = results[0]
    if len(results) == 1 or first.delta is None:
        return first.title
    values = ", ".join(f"{r.delta:g}" for r in results)
    if first.kind == "segments":
        return first.title.replace(f" over {first.delta:g} m ", f" over {values} m ", 1)
    return first.title.replace(f"delta = {first.delta:g} ", f"delta = {values} ", 1)


def plt_viridis_mid() -> Any:
    """The middle colour of the error colour map (the estimate's legend entry)."""
    import matplotlib

    return matplotlib.colormaps["viridis"](0.5)


def pyplot() -> Any:
    """matplotlib.pyplot on the Agg backend (headless; files only)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _top_view(
    ax: Any,
    fig: Any,
    ref_xyz: np.ndarray,
    est_xyz: np.ndarray,
    errors: np.ndarray,
    unit: str,
    est_label: str,
) -> None:
    from matplotlib import patheffects
    from matplotlib.collections import LineCollection

    # the estimate underneath, wide; the reference on top, thin, black and dashed with a white
    # edge, so that it shows where the two coincide, over any colour of the error map
    points = est_xyz[:, :2].reshape(-1, 1, 2)
    segments = np.concatenate([points[:-1], points[1:]], axis=1)
    seg_err = 0.5 * (errors[:-1] + errors[1:]) if len(errors) > 1 else errors
    lc = LineCollection(list(segments), cmap="viridis", linewidths=3.0, zorder=2)
    lc.set_array(seg_err)
    lc.set_clim(float(np.min(errors)), float(np.max(errors)))
    ax.add_collection(lc)
    ax.plot(
        ref_xyz[:, 0],
        ref_xyz[:, 1],
        "--",
        color="k",
        lw=0.9,
        dashes=(4, 3),
        zorder=3,
        label="reference",
        path_effects=[patheffects.Stroke(linewidth=2.4, foreground="white"), patheffects.Normal()],
    )
    ax.plot([], [], "-", color=plt_viridis_mid(), lw=3.0, label=est_label)
    ax.plot(est_xyz[0, 0], est_xyz[0, 1], "o", color="C3", ms=6, zorder=4, label="start")
    ax.autoscale()
    ax.set_aspect("equal", adjustable="datalim")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.legend(loc="best", fontsize=8)
    cbar = fig.colorbar(lc, ax=ax, shrink=0.85)
    cbar.set_label(f"error ({unit})" if unit else "error")
    ax.set_title("top view: estimate coloured by error, reference dashed", fontsize=10)


#: Summary lines over the error curve: distinct colours and styles, so that close values
#: (the mean and the median often are) stay apart.
_STAT_LINES = (("rmse", "-", "C3"), ("mean", "--", "C1"), ("median", ":", "C2"))
#: Error curves with fewer values than this get a marker on each value.
FEW_POINTS = 30


def _over_time(ax: Any, result: EvalResult, label: str | None = None) -> None:
    few = len(result.errors) < FEW_POINTS  # show a handful of values as points, not a curve
    ax.plot(
        result.t_s,
        result.errors,
        lw=1.0,
        marker="o" if few else None,
        ms=3,
        color="C0" if label is None else None,
        label=label or "error",
    )
    if label is None:
        for key, style, color in _STAT_LINES:
            ax.axhline(
                result.stats[key],
                ls=style,
                color=color,
                lw=1.6,
                label=f"{key} {result.stats[key]:.4g}",
            )
    untimed = result.association.get("method") == "index"
    ax.set_xlabel("pose index (no timestamps)" if untimed else "t (s, from the first pair)")
    name = {"ape": "APE", "rpe": "RPE", "segments": "drift"}[result.kind]
    ax.set_ylabel(f"{name} ({result.unit})" if result.unit else name)
    ax.grid(alpha=0.3)
    ax.legend(loc="best", fontsize=8)


def save_plots(path: str | Path, results: list[EvalResult], prepared: Any) -> list[Path]:
    """Write one figure for ``results`` (all of one kind) to ``path``; returns the files written."""
    plt = pyplot()
    out = Path(path)
    fig = figure(results, prepared)
    fig.savefig(out, dpi=110)
    plt.close(fig)
    return [out]


def figure(results: list[EvalResult], prepared: Any) -> Any:
    """The matplotlib figure of ``results`` (all of one kind); the caller closes it."""
    plt = pyplot()
    kind = results[0].kind
    if kind == "ape":
        r = results[0]
        fig, axes = plt.subplots(1, 2, figsize=(13, 5.2), gridspec_kw={"width_ratios": [1.1, 1.4]})
        _top_view(
            axes[0],
            fig,
            prepared.ref_poses[:, :3, 3],
            prepared.est_poses[:, :3, 3],
            r.errors,
            r.unit,
            "estimate" if r.alignment.get("method") in (None, "none") else "estimate (aligned)",
        )
        _over_time(axes[1], r)
        axes[1].set_title("error over time", fontsize=10)
    else:
        fig, axes = plt.subplots(1, 2, figsize=(13, 5.0), gridspec_kw={"width_ratios": [1.6, 1.0]})
        for r in results:
            lab = f"delta {r.delta:g} {r.delta_unit}" if kind == "rpe" else f"{r.delta:g} m"
            _over_time(axes[0], r, lab)
        axes[0].set_title(
            "error over time" if kind == "rpe" else "drift per sub-trajectory start", fontsize=10
        )
        labels = [f"{r.delta:g}" for r in results]
        axes[1].boxplot(
            [r.errors for r in results],
            tick_labels=labels,
            showfliers=True,
            flierprops={"markersize": 2},
        )
        unit_name = results[0].delta_unit or ""
        axes[1].set_xlabel(f"delta ({unit_name})" if kind == "rpe" else "sub-trajectory length (m)")
        axes[1].set_ylabel(f"{results[0].unit}" if results[0].unit else "error")
        axes[1].set_title("RPE per delta" if kind == "rpe" else "drift (% of length)", fontsize=10)
        axes[1].grid(alpha=0.3, axis="y")
    names = (
        f"estimate {display_name(results[0].estimate)} vs reference "
        f"{display_name(results[0].reference)}"
    )
    fig.suptitle(f"{joint_title(results)}\n{names}", fontsize=10)
    fig.tight_layout()
    return fig

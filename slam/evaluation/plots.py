"""Plots of evaluation results (matplotlib, Agg backend; PNG or PDF by the file suffix).

APE: top view of reference vs aligned estimate coloured by error, and error over time.
RPE: error over time per delta and box plots per delta. Segments: drift box plots per length.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from slam.evaluation.results import EvalResult


def _pyplot() -> Any:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _top_view(
    ax: Any, fig: Any, ref_xyz: np.ndarray, est_xyz: np.ndarray, errors: np.ndarray, unit: str
) -> None:
    from matplotlib.collections import LineCollection

    ax.plot(ref_xyz[:, 0], ref_xyz[:, 1], "--", color="0.45", lw=1.2, label="reference")
    points = est_xyz[:, :2].reshape(-1, 1, 2)
    segments = np.concatenate([points[:-1], points[1:]], axis=1)
    seg_err = 0.5 * (errors[:-1] + errors[1:]) if len(errors) > 1 else errors
    lc = LineCollection(list(segments), cmap="viridis", linewidths=2.0)
    lc.set_array(seg_err)
    lc.set_clim(float(np.min(errors)), float(np.max(errors)))
    ax.add_collection(lc)
    ax.plot(est_xyz[0, 0], est_xyz[0, 1], "o", color="k", ms=5, label="start")
    ax.autoscale()
    ax.set_aspect("equal", adjustable="datalim")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.legend(loc="best", fontsize=8)
    cbar = fig.colorbar(lc, ax=ax, shrink=0.85)
    cbar.set_label(f"error ({unit})" if unit else "error")
    ax.set_title("top view: estimate coloured by error", fontsize=10)


def _over_time(ax: Any, result: EvalResult, label: str | None = None) -> None:
    ax.plot(result.t_s, result.errors, lw=1.0, label=label or "error")
    if label is None:
        for key, style in (("rmse", "-"), ("mean", "--"), ("median", ":")):
            ax.axhline(
                result.stats[key],
                ls=style,
                color="C3" if key == "rmse" else "0.3",
                lw=1.0,
                label=f"{key} {result.stats[key]:.4g}",
            )
    untimed = result.association.get("method") == "index"
    ax.set_xlabel("pose index (no timestamps)" if untimed else "t (s, from the first pair)")
    name = {"ape": "APE", "rpe": "RPE", "segments": "drift"}[result.kind]
    ax.set_ylabel(f"{name} ({result.unit})" if result.unit else name)
    ax.grid(alpha=0.3)
    ax.legend(loc="upper left", fontsize=8)


def save_plots(path: str | Path, results: list[EvalResult], prepared: Any) -> list[Path]:
    """Write one figure for ``results`` (all of one kind) to ``path``; returns the files written."""
    plt = _pyplot()
    out = Path(path)
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
    title = results[0].title
    if len(results) > 1:  # one title for all deltas/lengths
        title = title.split(" for delta")[0].replace(
            f" over {results[0].delta:g} m", " over lengths"
        )
    names = f"{Path(results[0].estimate).name} vs {Path(results[0].reference).name}"
    fig.suptitle(f"{title}\n{names}", fontsize=10)
    fig.tight_layout()
    fig.savefig(out, dpi=110)
    plt.close(fig)
    return [out]

"""The batch report's figures: ATE box plots per configuration per sequence (as
rpg_trajectory_evaluation draws them), and every run's trajectory over the ground truth."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from slam.core.messages import BatchTask
from slam.evaluation.plots import pyplot

#: ATE panels of the box plot: (metric key, what the alignment is).
ATE_PANELS = (("ate_se3_m", "se3 alignment"), ("ate_posyaw_m", "posyaw (4-DoF) alignment"))


def _config_colours(configs: list[str]) -> dict[str, Any]:
    import matplotlib

    cmap = matplotlib.colormaps["tab10"]
    return {c: cmap(i % 10) for i, c in enumerate(configs)}


def _order(tasks: list[BatchTask]) -> tuple[list[str], list[str]]:
    sequences = list(dict.fromkeys(t.sequence for t in tasks))
    configs = list(dict.fromkeys(t.config for t in tasks))
    return sequences, configs


def ate_boxplot(path: Path, tasks: list[BatchTask], records: dict[str, dict[str, Any]]) -> bool:
    """Box plots of ATE RMSE over the repeats, one box per configuration per sequence, every
    repeat a dot on its box; one panel per alignment. False when there is nothing to draw."""
    from matplotlib.patches import Patch

    from slam.core.atomic import atomic_output

    sequences, configs = _order(tasks)
    values: dict[tuple[str, str, str], list[float]] = {}
    for t in tasks:
        r = records.get(t.run_id)
        if r is None or r.get("status") != "ok":
            continue
        for key, _ in ATE_PANELS:
            v = (r.get("metrics") or {}).get(key)
            if isinstance(v, (int, float)):
                values.setdefault((key, t.sequence, t.config), []).append(float(v))
    if not values:
        return False
    plt = pyplot()
    colours = _config_colours(configs)
    width = 0.8 / len(configs)
    fig, axes = plt.subplots(
        len(ATE_PANELS),
        1,
        figsize=(max(6.5, 1.2 + 1.6 * len(sequences) * max(1, len(configs) / 2)), 7.5),
        squeeze=False,
    )
    rng = np.random.default_rng(0)  # dot jitter only
    for ax, (key, alignment) in zip(axes[:, 0], ATE_PANELS):
        for i, seq in enumerate(sequences):
            for j, cfg in enumerate(configs):
                data = values.get((key, seq, cfg))
                if not data:
                    continue
                x = i + (j - (len(configs) - 1) / 2) * width
                box = ax.boxplot(
                    [data],
                    positions=[x],
                    widths=width * 0.8,
                    patch_artist=True,
                    showfliers=False,
                    medianprops={"color": "black"},
                )
                box["boxes"][0].set_facecolor((*colours[cfg][:3], 0.45))
                box["boxes"][0].set_edgecolor(colours[cfg])
                jitter = rng.uniform(-0.2, 0.2, len(data)) * width
                ax.plot(x + jitter, data, "o", ms=3.5, color=colours[cfg], mec="black", mew=0.4)
        ax.set_xticks(range(len(sequences)), sequences)
        ax.set_xlim(-0.6, len(sequences) - 0.4)
        ax.set_ylabel("ATE RMSE (m)")
        repeats = max((len(v) for v in values.values()), default=0)
        ax.set_title(
            f"ATE RMSE, {alignment} (boxes: quartiles over {repeats} repeat"
            f"{'s' if repeats != 1 else ''}; dots: runs)",
            fontsize=10,
        )
        ax.grid(alpha=0.3, axis="y")
        ax.set_ylim(bottom=0)
    axes[-1, 0].set_xlabel("sequence")
    handles = [
        Patch(facecolor=(*colours[c][:3], 0.45), edgecolor=colours[c], label=c) for c in configs
    ]
    axes[0, 0].legend(
        handles=handles,
        title="configuration",
        fontsize=8,
        loc="upper left",
        bbox_to_anchor=(1.0, 1.0),
    )
    fig.tight_layout()
    with atomic_output(path) as f:
        fig.savefig(f, dpi=110, format="png")
    plt.close(fig)
    return True


def trajectories_plot(
    path: Path, out_dir: Path, tasks: list[BatchTask], records: dict[str, dict[str, Any]]
) -> bool:
    """Top views, one per sequence: the ground truth and every run's estimate after posyaw
    alignment (as evaluated), coloured by configuration. False when there is nothing to draw."""
    from slam.core.atomic import atomic_output
    from slam.core.errors import SlamError
    from slam.evaluation.io import read_tum

    sequences, configs = _order(tasks)
    tracks: dict[str, list[tuple[str, np.ndarray]]] = {}
    reference: dict[str, np.ndarray] = {}
    for t in tasks:
        r = records.get(t.run_id)
        if r is None or r.get("status") != "ok":
            continue
        ev = out_dir / "runs" / t.run_id / "eval"
        try:
            est = read_tum(ev / "estimate_posyaw.tum", quiet=True).trajectory.positions_m
            if t.sequence not in reference:
                reference[t.sequence] = read_tum(
                    ev / "reference.tum", quiet=True
                ).trajectory.positions_m
        except (SlamError, OSError):  # no ground truth: nothing aligned to draw
            continue
        tracks.setdefault(t.sequence, []).append((t.config, est))
    shown = [s for s in sequences if s in tracks]
    if not shown:
        return False
    plt = pyplot()
    colours = _config_colours(configs)
    cols = min(3, len(shown))
    rows = (len(shown) + cols - 1) // cols
    fig, axes = plt.subplots(rows, cols, figsize=(5.2 * cols, 4.8 * rows), squeeze=False)
    for ax, seq in zip(axes.ravel(), shown):
        ref = reference[seq]
        labelled = set()
        for cfg, est in tracks[seq]:
            ax.plot(
                est[:, 0],
                est[:, 1],
                "-",
                lw=1.1,
                alpha=0.75,
                color=colours[cfg],
                label=None if cfg in labelled else cfg,
            )
            labelled.add(cfg)
        ax.plot(ref[:, 0], ref[:, 1], "--", color="black", lw=1.0, label="ground truth")
        ax.plot(ref[0, 0], ref[0, 1], "o", color="black", ms=5, label="start")
        ax.set_aspect("equal", adjustable="datalim")
        ax.set_xlabel("x (m)")
        ax.set_ylabel("y (m)")
        ax.set_title(seq, fontsize=10)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7, loc="best")
    for ax in axes.ravel()[len(shown) :]:
        ax.set_visible(False)
    fig.suptitle(
        "trajectories, top view: every run after posyaw alignment to the ground truth", fontsize=10
    )
    fig.tight_layout()
    with atomic_output(path) as f:
        fig.savefig(f, dpi=110, format="png")
    plt.close(fig)
    return True

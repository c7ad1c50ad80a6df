"""The evaluation plots: the reference shows on top of the estimate, the summary lines differ,
titles and subtitles say what is plotted."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from slam.core.trajectory import Trajectory
from slam.evaluation import evaluate as ev
from slam.evaluation import io as evio
from slam.evaluation import lie
from slam.evaluation.plots import display_name, figure, save_plots


def _sources() -> tuple[evio.PoseSource, evio.PoseSource]:
    n = 300
    t = np.arange(n) * 0.05
    pos = np.column_stack([3 * np.cos(0.3 * t), 2 * np.sin(0.6 * t), 0.1 * t])
    q = np.tile([1.0, 0.0, 0.0, 0.0], (n, 1))
    t_ns = 10**12 + np.arange(n, dtype=np.int64) * 50_000_000
    noisy = pos + np.random.default_rng(0).normal(scale=0.02, size=pos.shape)
    out = []
    for name, p in (("room.mcap:/groundtruth/pose", pos), ("/data/runs/run1", noisy)):
        traj = Trajectory(t_ns, p, q)
        poses = lie.poses_from_pq(traj.positions_m, traj.q_wxyz)
        out.append(evio.PoseSource(traj, poses, name, name, "tum"))
    return out[0], out[1]


def _prepared(align: str) -> ev.Prepared:
    return ev.prepare(*_sources(), ev.EvalOptions(align=align))


def test_ape_plot_reference_on_top_and_distinct_summary_lines(tmp_path: Path) -> None:
    import matplotlib.pyplot as plt

    p = _prepared("posyaw")
    fig = figure([ev.ape_of(p)], p)
    top, over_time = fig.axes[0], fig.axes[1]
    ref = next(ln for ln in top.lines if ln.get_label() == "reference")
    estimate = top.collections[0]
    assert ref.get_zorder() > estimate.get_zorder() and ref.get_linestyle() == "--"
    edge = ref.get_path_effects()[0]  # a white edge keeps it visible over dark error colours
    assert edge._gc["foreground"] == "white" and edge._gc["linewidth"] > ref.get_linewidth()
    assert [t.get_text() for t in top.get_legend().get_texts()] == [
        "reference",
        "estimate (aligned)",
        "start",
    ]
    stats = {ln.get_label().split()[0]: ln for ln in over_time.lines[1:]}
    assert sorted(stats) == ["mean", "median", "rmse"]
    styles = {(str(ln.get_color()), ln.get_linestyle()) for ln in stats.values()}
    assert len(styles) == 3  # no two summary lines look alike
    assert fig._suptitle.get_text().splitlines()[1] == (
        "estimate run1 vs reference room.mcap /groundtruth/pose"
    )
    plt.close(fig)
    assert save_plots(tmp_path / "ape.png", [ev.ape_of(p)], p)[0].stat().st_size > 10_000


def test_titles_of_several_deltas_and_lengths() -> None:
    import matplotlib.pyplot as plt

    p = _prepared("none")
    fig = figure([ev.rpe_of(p, delta=d) for d in (1, 5)], p)
    assert fig._suptitle.get_text().splitlines()[0] == (
        "RPE w.r.t. translation part (m) for delta = 1, 5 frames using consecutive pairs "
        "(not aligned)"
    )
    delta1, delta5 = fig.axes[0].lines  # 299 and 59 values: curves; a handful: markers
    assert delta1.get_marker() in (None, "None") and delta5.get_marker() in (None, "None")
    plt.close(fig)
    fig = figure([ev.rpe_of(p, delta=60)], p)
    assert fig.axes[0].lines[0].get_marker() == "o"
    plt.close(fig)
    p = _prepared("se3")
    fig = figure(ev.segments_of(p, (2.0, 5.0), step=5), p)
    assert fig._suptitle.get_text().splitlines()[0] == (
        "relative error over 2, 5 m sub-trajectories (drift % of length) (SE(3) Umeyama alignment)"
    )
    plt.close(fig)
    p = _prepared("none")
    fig = figure([ev.ape_of(p)], p)
    assert "estimate" in [t.get_text() for t in fig.axes[0].get_legend().get_texts()]
    plt.close(fig)


def test_display_names() -> None:
    assert display_name("room.mcap:/groundtruth/pose") == "room.mcap /groundtruth/pose"
    assert display_name("/data/V1_01_easy/mav0/state_groundtruth_estimate0/data.csv") == "data.csv"
    assert display_name("run1") == "run1"

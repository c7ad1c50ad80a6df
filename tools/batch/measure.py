"""A finished run's numbers: accuracy against the sequence's ground truth and its stats.

Accuracy goes through ``slam.evaluation`` (the same numbers as `slam eval`): ATE RMSE with se3
and posyaw alignment, RPE at 1 m and 10 m, drift (% of distance over sub-trajectories of 10-50 %
of the path, rpg style), the loop-closed trajectory's ATE, false loops. The stats are
``stats.json`` summarised: completion, real-time factor, latencies, memory. ``slam bench`` and
``slam batch`` both tabulate these rows (``COLUMNS``).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from slam.core.errors import SlamError
from slam.core.geometry import rotation_angle_rad


def ate_se3(seq_path: Path, trajectory: Path, from_t_ns: int | None = None) -> float | None:
    """ATE RMSE (SE3 alignment) of one trajectory file or run folder against the sequence.

    ``from_t_ns``: the RMSE over the poses from that time on only (aligned on all of them, as
    the whole-run figure): the part of a run after its first revisit, where a causal pose can
    use what the loop closure found; before it, only the odometry exists.
    """
    from slam.evaluation.evaluate import EvalOptions, ape_of, load_pair, prepare

    try:
        ref, est = load_pair(seq_path, trajectory, EvalOptions())
        p = prepare(ref, est, EvalOptions(align="se3"))
    except SlamError:
        return None
    res = ape_of(p)
    if from_t_ns is None:
        return float(res.stats["rmse"])
    after = np.asarray(p.association.t_ns) >= from_t_ns
    if not after.any():
        return None
    return float(np.sqrt(np.mean(np.square(np.asarray(res.errors)[after]))))


def scale_error_pct(seq_path: Path, trajectory: Path) -> float | None:
    """|Sim(3) scale - 1| in % of one trajectory file against the sequence (None when it
    cannot be aligned). Of the loop-closed trajectory it is the part of its ATE that no
    reprojection can remove in a monocular map: the global adjustment holds the map's scale
    only by the odometry edges (BENCHMARKS.md, mono18lc)."""
    from slam.evaluation.evaluate import EvalOptions, load_pair, prepare

    try:
        ref, est = load_pair(seq_path, trajectory, EvalOptions())
        scale = prepare(ref, est, EvalOptions(align="sim3")).alignment.scale
    except SlamError:
        return None
    return 100.0 * abs(float(scale) - 1.0)


def evaluate_run(seq_path: Path, run_dir: Path, artefacts: Path | None = None) -> dict[str, Any]:
    """Accuracy of a run against the sequence's ground truth (``eval_error`` when it has none).

    With ``artefacts``, also writes there the APE results (``ape_se3.json``,
    ``ape_posyaw.json``, as `slam eval --json`) and the posyaw-aligned estimate with its
    associated reference poses (``estimate_posyaw.tum``, ``reference.tum``: the batch's
    trajectory plots).
    """
    from slam.core.trajectory import Trajectory
    from slam.evaluation.evaluate import (
        EvalOptions,
        ape_of,
        load_pair,
        prepare,
        resolve_lengths,
        rpe_of,
        segments_of,
    )
    from slam.evaluation.io import write_tum
    from slam.evaluation.results import write_json

    try:
        ref, est = load_pair(seq_path, run_dir, EvalOptions())
        p_se3 = prepare(ref, est, EvalOptions(align="se3"))
        p_yaw = prepare(ref, est, EvalOptions(align="posyaw"))
    except SlamError as exc:  # no ground truth, a degenerate path (standing still)
        return {"eval_error": str(exc)}
    out: dict[str, Any] = {}
    ape_se3, ape_yaw = ape_of(p_se3), ape_of(p_yaw)
    out["ate_se3_m"] = ape_se3.stats["rmse"]
    out["ate_posyaw_m"] = ape_yaw.stats["rmse"]
    out["gt_path_m"] = ref.trajectory.path_length_m()
    try:  # the live trajectory's scale error: |Sim(3) scale - 1|, as issues 17 and 18 state it
        sim3 = prepare(ref, est, EvalOptions(align="sim3")).alignment
        out["scale_error_pct"] = 100.0 * abs(sim3.scale - 1.0)
    except SlamError:
        out["scale_error_pct"] = None
    for delta in (1.0, 10.0):
        try:
            out[f"rpe_{delta:g}m_m"] = rpe_of(p_se3, "trans", delta, "metres").stats["rmse"]
        except Exception:  # path shorter than the delta
            out[f"rpe_{delta:g}m_m"] = None
    closed = run_dir / "trajectory_loop_closed.tum"
    if closed.exists():
        out["ate_loop_closed_m"] = ate_se3(seq_path, closed)
        out["scale_error_loop_closed_pct"] = scale_error_pct(seq_path, closed)
    odometry = run_dir / "trajectory_odometry.tum"
    if odometry.exists():
        out["ate_odometry_m"] = ate_se3(seq_path, odometry)
    try:
        with np.errstate(all="ignore"):  # a path of a few cm: segments of zero length
            segs = segments_of(p_yaw, resolve_lengths("rpg", p_yaw.ref_poses))
        drift = float(sum(s.stats["mean"] for s in segs) / len(segs))
        out["drift_pct"] = drift if np.isfinite(drift) else None
    except Exception:
        out["drift_pct"] = None
    if artefacts is not None:
        write_json(artefacts / "ape_se3.json", [ape_se3])
        write_json(artefacts / "ape_posyaw.json", [ape_yaw])
        t_ns = p_yaw.association.t_ns
        write_tum(
            artefacts / "estimate_posyaw.tum", Trajectory.from_matrices(t_ns, p_yaw.est_poses)
        )
        write_tum(artefacts / "reference.tum", Trajectory.from_matrices(t_ns, p_yaw.ref_poses))
    return out


def false_loops(seq_path: Path, stats: dict[str, Any]) -> int | None:
    """Accepted loops whose two keyframes were not at the same place by the ground truth.

    Same place: body positions within 2 m and camera viewing directions within 45 degrees (a
    verified loop needs shared structure in view). None without ground truth or loops.
    """
    loops = (stats.get("loop_closure") or {}).get("loops")
    if not loops:
        return 0 if loops is not None else None
    from datasets.open import open_sequence
    from slam.core.geometry import quat_wxyz_to_matrix

    gt = open_sequence(seq_path).ground_truth
    if gt is None or len(gt) == 0:
        return None

    def pose_at(t_ns: int) -> tuple[np.ndarray, np.ndarray]:
        i = int(np.clip(np.searchsorted(gt.t_ns, t_ns), 0, len(gt) - 1))
        return gt.positions_m[i], quat_wxyz_to_matrix(gt.q_wxyz[i])

    false = 0
    for loop in loops:
        if loop.get("query_t_ns") is None or loop.get("match_t_ns") is None:
            continue
        pa, ra = pose_at(int(loop["query_t_ns"]))
        pb, rb = pose_at(int(loop["match_t_ns"]))
        # EuRoC-style body: the camera looks along body x/z; compare all axes' agreement
        angle_deg = float(np.degrees(rotation_angle_rad(ra.T @ rb)))
        if np.linalg.norm(pa - pb) > 2.0 or angle_deg > 45.0:
            false += 1
    return false


def summarise(name: str, stats: dict[str, Any], acc: dict[str, Any]) -> dict[str, Any]:
    """One table row: the accuracy ``acc`` and the run's ``stats.json`` figures."""
    be = stats.get("backend") or {}
    fe = stats.get("latency", {}).get("frontend_frame", {})
    frames_in = max(int(stats.get("frames_in", 0)), 1)
    return {
        "sequence": name,
        **acc,
        "completion_pct": 100.0 * stats.get("frames_tracked", 0) / frames_in,
        "tracking_losses": stats.get("tracking_losses"),
        "loops_accepted": (stats.get("loop_closure") or {}).get("accepted"),
        "init_s": be.get("initialised_after_s"),
        "real_time_factor": stats.get("real_time_factor"),
        "frontend_p50_ms": fe.get("p50_ms"),
        "frontend_p99_ms": fe.get("p99_ms"),
        # of the p99 frame time, how much a frame's CPU work and its run-queue wait take (p99s)
        "frontend_cpu_p99_ms": stats.get("latency", {}).get("frontend_frame_cpu", {}).get("p99_ms"),
        "frontend_runqueue_p99_ms": (
            stats.get("latency", {}).get("frontend_frame_runqueue", {}).get("p99_ms")
        ),
        "backend_p50_ms": (be.get("update") or {}).get("p50_ms"),
        "backend_p99_ms": (be.get("update") or {}).get("p99_ms"),
        "backend_resets": be.get("resets"),
        "peak_rss_mb": stats.get("peak_rss_mb"),
        "end_of_run_s": stats.get("end_of_run_s"),
        "keyframes": stats.get("keyframes"),
        "old_landmarks_on_revisits": (stats.get("map_reuse") or {}).get(
            "old_landmark_fraction_on_revisits"
        ),
    }


def measure_run(seq_path: Path, run_dir: Path, name: str) -> dict[str, Any]:
    """Everything tabulated about a finished run in ``run_dir`` (evaluation files go to
    ``run_dir/eval``)."""
    import json

    stats: dict[str, Any] = json.loads((run_dir / "stats.json").read_text())
    acc = evaluate_run(seq_path, run_dir, run_dir / "eval")
    acc["false_loops"] = false_loops(seq_path, stats)
    loops = (stats.get("loop_closure") or {}).get("loops") or []
    first = min((int(lp["query_t_ns"]) for lp in loops if lp.get("query_t_ns")), default=None)
    if first is not None:
        acc["ate_live_after_loop_m"] = ate_se3(seq_path, run_dir / "trajectory.tum", first)
        closed = run_dir / "trajectory_loop_closed.tum"
        if closed.exists():
            acc["ate_loop_closed_after_loop_m"] = ate_se3(seq_path, closed, first)
    return summarise(name, stats, acc)


#: (key, title, format) of the tabulated numbers, in table order.
COLUMNS = (
    ("sequence", "sequence", "{}"),
    ("ate_se3_m", "ATE se3 (m)", "{:.4f}"),
    ("ate_posyaw_m", "ATE posyaw (m)", "{:.4f}"),
    ("ate_odometry_m", "ATE odometry (m)", "{:.4f}"),
    ("ate_loop_closed_m", "ATE loop-closed (m)", "{:.4f}"),
    ("ate_loop_off_m", "ATE loop off (m)", "{:.4f}"),
    ("loop_ratio", "closed/off", "{:.2f}"),
    ("ate_live_after_loop_m", "ATE live after 1st loop (m)", "{:.4f}"),
    ("ate_loop_closed_after_loop_m", "ATE loop-closed after 1st loop (m)", "{:.4f}"),
    ("scale_error_pct", "scale error (%)", "{:.2f}"),
    ("scale_error_loop_closed_pct", "loop-closed scale error (%)", "{:.2f}"),
    ("rpe_1m_m", "RPE 1 m (m)", "{:.4f}"),
    ("rpe_10m_m", "RPE 10 m (m)", "{:.4f}"),
    ("drift_pct", "drift (%)", "{:.3f}"),
    ("completion_pct", "completion (%)", "{:.1f}"),
    ("loops_accepted", "loops", "{}"),
    ("false_loops", "false loops", "{}"),
    ("old_landmarks_on_revisits", "old landmarks on revisits", "{:.2f}"),
    ("init_s", "init (s)", "{:.2f}"),
    ("real_time_factor", "RTF", "{:.2f}"),
    ("end_of_run_s", "end (s)", "{:.1f}"),
    ("frontend_p50_ms", "FE p50 (ms)", "{:.1f}"),
    ("frontend_p99_ms", "FE p99 (ms)", "{:.1f}"),
    ("backend_p50_ms", "BE p50 (ms)", "{:.1f}"),
    ("backend_p99_ms", "BE p99 (ms)", "{:.1f}"),
    ("peak_rss_mb", "peak memory (MB)", "{:.0f}"),
)


def fmt(value: Any, spec: str) -> str:
    """``value`` formatted by ``spec``; ``-`` for None."""
    if value is None:
        return "-"
    try:
        return spec.format(value)
    except (ValueError, TypeError):
        return str(value)

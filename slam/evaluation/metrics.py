"""Pose errors on associated, aligned poses (batched numpy; the same formulas as evo 1.38).

APE at each pair: E = est^-1 ref; RPE over a pair (i, j): E = (ref_i^-1 ref_j)^-1 (est_i^-1 est_j).
Relations (``RELATIONS``) turn E into one number:
  trans      |t_E| (m); for APE evo takes |p_est - p_ref|, which is the same number
  angle_deg  rotation angle of E (deg);  angle_rad: the same in rad
  rot        ||R_E - I||_F (evo "rot_part", unitless)
  full       ||E - I||_F (unitless)
RPE deltas: ``frames`` (index steps), ``seconds`` and ``metres`` (path length travelled along
the estimate, evo's rule); consecutive pairs, or all pairs.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from slam.core.errors import InputError
from slam.evaluation import lie

RELATIONS = ("trans", "angle_deg", "angle_rad", "rot", "full")
RELATION_UNITS = {"trans": "m", "angle_deg": "deg", "angle_rad": "rad", "rot": "", "full": ""}
RELATION_TITLES = {
    "trans": "translation part",
    "angle_deg": "rotation angle in degrees",
    "angle_rad": "rotation angle in radians",
    "rot": "rotation part",
    "full": "full transformation",
}
DELTA_UNITS = ("frames", "seconds", "metres")
STATISTICS = ("rmse", "mean", "median", "std", "min", "max", "sse")


def _median(e: np.ndarray) -> float:
    """np.median's value bit for bit (mean of the two middle values), without the ~20 ms
    numpy.ma import that np.median triggers on first use."""
    n = len(e)
    k = n // 2
    if n % 2:
        return float(np.partition(e, k)[k])
    part = np.partition(e, [k - 1, k])
    return float((part[k - 1] + part[k]) / 2.0)


def statistics(errors: np.ndarray) -> dict[str, float]:
    """rmse, mean, median, std, min, max, sse of an error array (evo's formulas)."""
    e = np.asarray(errors, dtype=np.float64).ravel()
    if e.size == 0:
        raise InputError("no errors to summarise (no pose pairs)")
    sq = np.power(e, 2)
    return {
        "rmse": math.sqrt(float(np.mean(sq))),
        "mean": float(np.mean(e)),
        "median": _median(e),
        "std": float(np.std(e)),
        "min": float(np.min(e)),
        "max": float(np.max(e)),
        "sse": float(np.sum(sq)),
    }


def relation_errors(e_poses: np.ndarray, relation: str) -> np.ndarray:
    """One number per (N, 4, 4) error pose."""
    if relation == "trans":
        return np.linalg.norm(e_poses[:, :3, 3], axis=1)
    if relation in ("angle_deg", "angle_rad"):
        angles = lie.rotation_angles_rad(e_poses[:, :3, :3])
        return np.rad2deg(angles) if relation == "angle_deg" else angles
    if relation == "rot":
        return np.linalg.norm(e_poses[:, :3, :3] - np.eye(3), axis=(1, 2))
    if relation == "full":
        return np.linalg.norm(e_poses - np.eye(4), axis=(1, 2))
    raise InputError(f"unknown pose relation {relation!r}; choose one of {', '.join(RELATIONS)}")


def ape_errors(ref_poses: np.ndarray, est_poses: np.ndarray, relation: str) -> np.ndarray:
    """Absolute pose error per associated pair."""
    if relation == "trans":
        return np.linalg.norm(est_poses[:, :3, 3] - ref_poses[:, :3, 3], axis=1)
    return relation_errors(lie.relative(est_poses, ref_poses), relation)


# --------------------------------------------------------------------------------------------
# RPE pairs


def accumulated_distances(positions_m: np.ndarray) -> np.ndarray:
    """Path length from the first pose to each pose (evo's expression, bit for bit)."""
    return np.concatenate(
        (np.array([0.0]), np.cumsum(np.linalg.norm(positions_m[:-1] - positions_m[1:], axis=1)))
    )


def _pairs_by_path_consecutive(positions_m: np.ndarray, delta: float) -> np.ndarray:
    """evo's greedy rule: the next pose once the path since the last one reaches ``delta``."""
    steps = np.linalg.norm(positions_m[1:] - positions_m[:-1], axis=1)
    global_cum = np.cumsum(steps)
    ids = [0]
    i = 0  # current start pose
    n = len(positions_m)
    while i < n - 1:
        base = global_cum[i - 1] if i > 0 else 0.0
        guess = int(np.searchsorted(global_cum, base + delta, side="left"))
        stop = min(len(steps), max(guess + 8, i + 8))
        while True:
            local = np.cumsum(steps[i:stop])  # sequential sum restarted at 0, as evo's loop
            hit = np.nonzero(local >= delta)[0]
            if len(hit) or stop >= len(steps):
                break
            stop = min(len(steps), stop + max(64, stop - i))
        if not len(hit):
            break
        i = i + int(hit[0]) + 1
        ids.append(i)
    ids_a = np.asarray(ids)
    return np.column_stack([ids_a[:-1], ids_a[1:]])


def _pairs_by_path_all(positions_m: np.ndarray, delta: float, tol: float) -> np.ndarray:
    """For each i, the j > i whose path distance from i is closest to ``delta`` (within tol)."""
    d = accumulated_distances(positions_m)
    n = len(d)
    i = np.arange(n - 1)
    k = np.searchsorted(d, d[i] + delta, side="left")
    cand_hi = np.minimum(np.maximum(k, i + 1), n - 1)
    lo_val = d[np.clip(k - 1, 0, n - 1)]
    cand_lo = np.searchsorted(d, lo_val, side="left")  # first index of that plateau (argmin)
    cand_lo = np.maximum(cand_lo, i + 1)
    cand_lo = np.minimum(cand_lo, n - 1)
    err_lo = np.abs((d[cand_lo] - d[i]) - delta)
    err_hi = np.abs((d[cand_hi] - d[i]) - delta)
    j = np.where(err_lo <= err_hi, cand_lo, cand_hi)
    err = np.minimum(err_lo, err_hi)
    keep = err <= tol
    return np.column_stack([i[keep], j[keep]])


def _pairs_by_time(t_ns: np.ndarray, delta_s: float, tol: float, all_pairs: bool) -> np.ndarray:
    """Pairs whose time difference is closest to ``delta_s`` (within ``tol`` * delta)."""
    n = len(t_ns)
    delta_ns = delta_s * 1e9

    def nearest(i: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        target = t_ns[i] + delta_ns
        k = np.clip(np.searchsorted(t_ns, target, side="left"), 1, n - 1)
        lo, hi = np.maximum(k - 1, i + 1), np.maximum(k, i + 1)
        hi = np.minimum(hi, n - 1)
        lo = np.minimum(lo, n - 1)
        err_lo = np.abs(t_ns[lo] - target)
        err_hi = np.abs(t_ns[hi] - target)
        j = np.where(err_lo <= err_hi, lo, hi)
        return j, np.minimum(err_lo, err_hi)

    if all_pairs:
        starts = np.arange(n - 1)
        ends, err = nearest(starts)
        keep = err <= tol * delta_ns
        return np.column_stack([starts[keep], ends[keep]])
    pairs = []
    start = 0
    while start < n - 1:
        end_arr, err_arr = nearest(np.array([start]))
        end = int(end_arr[0])
        if err_arr[0] <= tol * delta_ns:
            pairs.append((start, end))
        start = end
    return np.array(pairs, dtype=np.int64).reshape(-1, 2)


def rpe_pairs(
    est_poses: np.ndarray,
    t_ns: np.ndarray,
    delta: float,
    unit: str,
    *,
    all_pairs: bool = False,
    rel_tol: float = 0.1,
) -> np.ndarray:
    """(M, 2) index pairs (i, j) for RPE with ``delta`` in ``unit`` (frames/seconds/metres)."""
    n = len(est_poses)
    if delta <= 0:
        raise InputError(f"--delta must be positive (got {delta})")
    if unit == "frames":
        if float(delta) != int(delta):
            raise InputError(f"--delta must be a whole number of frames (got {delta})")
        step = int(delta)
        if all_pairs:
            i = np.arange(max(n - step, 0))
        else:
            ids = np.arange(0, n, step)
            i = ids[:-1]
        pairs = np.column_stack([i, i + step])
    elif unit == "metres":
        positions = est_poses[:, :3, 3]
        pairs = (
            _pairs_by_path_all(positions, delta, delta * rel_tol)
            if all_pairs
            else _pairs_by_path_consecutive(positions, delta)
        )
    elif unit == "seconds":
        pairs = _pairs_by_time(t_ns, delta, rel_tol, all_pairs)
    else:
        raise InputError(f"unknown delta unit {unit!r}; choose one of {', '.join(DELTA_UNITS)}")
    if len(pairs) == 0:
        raise InputError(
            f"delta {delta} {unit} gives no pose pairs ({n} poses); use a smaller --delta"
        )
    return pairs.astype(np.int64)


def rpe_errors(
    ref_poses: np.ndarray, est_poses: np.ndarray, pairs: np.ndarray, relation: str
) -> np.ndarray:
    """Relative pose error over each pair (i, j)."""
    i, j = pairs[:, 0], pairs[:, 1]
    q_rel = lie.relative(ref_poses[i], ref_poses[j])
    p_rel = lie.relative(est_poses[i], est_poses[j])
    return relation_errors(lie.relative(q_rel, p_rel), relation)


# --------------------------------------------------------------------------------------------
# relative error over sub-trajectory lengths (KITTI devkit / rpg style)

KITTI_LENGTHS_M = (100.0, 200.0, 300.0, 400.0, 500.0, 600.0, 700.0, 800.0)
RPG_FRACTIONS = (0.1, 0.2, 0.3, 0.4, 0.5)


@dataclass(frozen=True, eq=False)
class SegmentErrors:
    """Errors of every sub-trajectory of one length: start indices, and per segment the
    translation error (m), drift (% of length) and rotation drift (deg/m)."""

    length_m: float
    start_index: np.ndarray
    trans_err_m: np.ndarray
    drift_pct: np.ndarray
    rot_deg_per_m: np.ndarray


def segment_errors(
    ref_poses: np.ndarray, est_poses: np.ndarray, lengths_m: tuple[float, ...], step: int = 10
) -> list[SegmentErrors]:
    """For starts every ``step`` poses and each length, the first pose at least that far along the
    reference path: E = (ref_i^-1 ref_j)^-1 (est_i^-1 est_j), errors divided by the length."""
    d = accumulated_distances(ref_poses[:, :3, 3])
    starts = np.arange(0, len(d), max(1, step))
    out = []
    for length in lengths_m:
        ends = np.searchsorted(d, d[starts] + length, side="left")
        ok = ends < len(d)
        i, j = starts[ok], ends[ok]
        if len(i) == 0:
            out.append(SegmentErrors(float(length), i, np.zeros(0), np.zeros(0), np.zeros(0)))
            continue
        e = lie.relative(
            lie.relative(ref_poses[i], ref_poses[j]), lie.relative(est_poses[i], est_poses[j])
        )
        t_err = np.linalg.norm(e[:, :3, 3], axis=1)
        r_err = np.rad2deg(lie.rotation_angles_rad(e[:, :3, :3]))
        out.append(SegmentErrors(float(length), i, t_err, 100.0 * t_err / length, r_err / length))
    return out

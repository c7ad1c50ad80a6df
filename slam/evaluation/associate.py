"""Pair reference and estimate poses in time.

``nearest``: evo's ``matching_time_indices`` rule, vectorised: start from the trajectory with
fewer poses, take the closest stamp of the other within ``max_diff`` (ties go to the earlier
one); several poses of the shorter one may pair with the same pose of the longer one, exactly
as in evo. ``interpolate``: the reference is interpolated at the estimate's times (linear
position, SLERP rotation), for estimate poses inside the reference's time range only.
Times are int64 ns throughout; ``t_offset_ns`` is added to the estimate's clock.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from slam.core.errors import InputError
from slam.evaluation import lie
from slam.evaluation.io import PoseSource

log = logging.getLogger(__name__)


@dataclass(frozen=True, eq=False)
class Association:
    """Matched poses: ``ref_poses[k]`` belongs with ``est_poses[k]``.

    ``t_ns`` are the estimate's times of the pairs (estimate clock); ``ref_index`` is -1 for
    interpolated reference poses; ``est_index`` indexes the estimate as read.
    """

    t_ns: np.ndarray
    ref_poses: np.ndarray
    est_poses: np.ndarray
    ref_index: np.ndarray
    est_index: np.ndarray
    method: str
    max_diff_ns: int
    t_offset_ns: int

    def __len__(self) -> int:
        return len(self.t_ns)


def matching_indices(
    stamps_short: np.ndarray, stamps_long: np.ndarray, max_diff: float, offset_long: float = 0.0
) -> tuple[np.ndarray, np.ndarray]:
    """Indices (short, long) of nearest-stamp matches within ``max_diff`` (evo's rule).

    Works on float seconds exactly as evo does, so ties and boundary cases pair identically.
    """
    long = stamps_long + offset_long
    s = stamps_short
    inside = ~((s < long[0] - max_diff) | (s > long[-1] + max_diff))
    idx = np.searchsorted(long, s, side="right")
    idx = np.minimum(idx, len(long) - 1)
    diff_ub = long[idx] - s
    diff_lb = np.where(idx > 0, s - long[np.maximum(idx - 1, 0)], np.inf)
    use_ub = (diff_ub <= max_diff) & (diff_ub < diff_lb)
    use_lb = ~use_ub & (diff_lb <= max_diff) & (diff_lb <= diff_ub)
    ok = inside & (use_ub | use_lb)
    best = np.where(use_ub, idx, idx - 1)
    return np.nonzero(ok)[0], best[ok]


def _range_hint(ref: PoseSource, est: PoseSource, t_offset_ns: int) -> str:
    """Explain non-overlapping time ranges, spotting the ns-vs-s (factor ~1e9) mistake."""
    r0, r1 = int(ref.trajectory.t_ns[0]), int(ref.trajectory.t_ns[-1])
    e0 = int(est.trajectory.t_ns[0]) + t_offset_ns
    e1 = int(est.trajectory.t_ns[-1]) + t_offset_ns
    msg = (
        f"time ranges do not overlap: reference {ref.name} {r0 * 1e-9:.3f}..{r1 * 1e-9:.3f} s, "
        f"estimate {est.name} {e0 * 1e-9:.3f}..{e1 * 1e-9:.3f} s"
    )
    mid_r, mid_e = abs(0.5 * (r0 + r1)), abs(0.5 * (e0 + e1))
    if mid_r > 0 and mid_e > 0:
        ratio = max(mid_r, mid_e) / min(mid_r, mid_e)
        if 1e8 <= ratio <= 1e10:
            bigger = ref.name if mid_r > mid_e else est.name
            flag = "--ref-time-unit" if mid_r > mid_e else "--est-time-unit"
            msg += (
                f"; they differ by a factor of ~{ratio:.2g}: {bigger} probably holds nanoseconds "
                f"where seconds were expected: pass {flag} ns"
            )
            return msg
    msg += "; use --t-offset SECONDS if the clocks differ"
    return msg


def associate(
    ref: PoseSource,
    est: PoseSource,
    *,
    max_diff_s: float = 0.01,
    t_offset_s: float = 0.0,
    interpolate: bool = False,
) -> Association:
    """Pair the poses of ``ref`` and ``est`` (see the module docstring)."""
    max_diff_ns = round(max_diff_s * 1e9)
    t_offset_ns = round(t_offset_s * 1e9)
    if not (ref.timed and est.timed):
        if len(ref) != len(est):
            raise InputError(
                f"{ref.name if not ref.timed else est.name} has no timestamps (KITTI without a "
                f"times file), so poses pair by index, but the counts differ ({len(ref)} vs "
                f"{len(est)}); give --ref-times/--est-times"
            )
        idx = np.arange(len(ref))
        return Association(
            est.trajectory.t_ns, ref.world_from_body, est.world_from_body, idx, idx, "index", 0, 0
        )
    t_ref = ref.trajectory.t_ns
    t_est = est.trajectory.t_ns
    overlap = (t_est[0] + t_offset_ns <= t_ref[-1] + max_diff_ns) and (
        t_ref[0] <= t_est[-1] + t_offset_ns + max_diff_ns
    )
    if not overlap:
        raise InputError(_range_hint(ref, est, t_offset_ns))
    if interpolate:
        return _interpolated(ref, est, t_offset_ns, max_diff_ns)
    s_ref, s_est = ref.seconds, est.seconds
    if len(est) > len(ref):
        i_ref, i_est = matching_indices(s_ref, s_est, max_diff_s, t_offset_s)
    else:
        i_est, i_ref = matching_indices(s_est, s_ref, max_diff_s, -t_offset_s)
    if len(i_ref) == 0:
        raise InputError(
            f"no pose pairs within --max-diff {max_diff_s} s between {ref.name} and {est.name} "
            f"(time offset {t_offset_s} s); raise --max-diff or use --interpolate"
        )
    log.debug("associated %d of max. %d poses", len(i_ref), min(len(ref), len(est)))
    return Association(
        t_est[i_est],
        ref.world_from_body[i_ref],
        est.world_from_body[i_est],
        i_ref,
        i_est,
        "nearest",
        max_diff_ns,
        t_offset_ns,
    )


def interpolate_poses(
    t_ns: np.ndarray, positions_m: np.ndarray, q_wxyz: np.ndarray, t_query_ns: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Positions (linear) and quaternions (SLERP) at ``t_query_ns`` inside [t_ns[0], t_ns[-1]]."""
    idx = np.clip(np.searchsorted(t_ns, t_query_ns, side="left"), 1, len(t_ns) - 1)
    t0, t1 = t_ns[idx - 1], t_ns[idx]
    frac = ((t_query_ns - t0) / (t1 - t0)).astype(np.float64)
    p = positions_m[idx - 1] + frac[:, None] * (positions_m[idx] - positions_m[idx - 1])
    q = lie.slerp_wxyz(q_wxyz[idx - 1], q_wxyz[idx], frac)
    return p, q


def _interpolated(
    ref: PoseSource, est: PoseSource, t_offset_ns: int, max_diff_ns: int
) -> Association:
    if len(ref) < 2:
        raise InputError(f"{ref.name}: interpolation needs at least two reference poses")
    t_ref = ref.trajectory.t_ns
    t_query = est.trajectory.t_ns + t_offset_ns
    inside = (t_query >= t_ref[0]) & (t_query <= t_ref[-1])
    i_est = np.nonzero(inside)[0]
    if len(i_est) == 0:
        raise InputError(_range_hint(ref, est, t_offset_ns))
    dropped = len(est) - len(i_est)
    if dropped:
        log.info("interpolation: %d estimate poses lie outside the reference's time range", dropped)
    p, q = interpolate_poses(
        t_ref, ref.trajectory.positions_m, ref.trajectory.q_wxyz, t_query[i_est]
    )
    return Association(
        est.trajectory.t_ns[i_est],
        lie.poses_from_pq(p, q),
        est.world_from_body[i_est],
        np.full(len(i_est), -1),
        i_est,
        "interpolate",
        max_diff_ns,
        t_offset_ns,
    )

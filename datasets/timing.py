"""Timestamp hygiene shared by every reader: sorting, de-duplication, stereo pairing, gaps.

Each function returns what it changed, so readers can put the counts in a warning: data-quality
problems are never fixed silently.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Cleaned:
    """Indices (into the original arrays) that keep a strictly increasing time series."""

    keep: np.ndarray  # int64 indices, in time order
    out_of_order: int  # samples that came earlier than their predecessor (now sorted)
    duplicates: int  # samples with the timestamp of an earlier one (dropped, first kept)

    def describe(self, what: str) -> str | None:
        """A warning sentence, or None when the series was already clean."""
        parts = []
        if self.out_of_order:
            parts.append(f"{self.out_of_order} out of time order (sorted)")
        if self.duplicates:
            parts.append(f"{self.duplicates} with duplicate timestamps (dropped)")
        return f"{what}: " + ", ".join(parts) if parts else None


def sort_dedupe(t_ns: np.ndarray) -> Cleaned:
    """Stable sort by time, then drop repeats of a timestamp (the first occurrence wins)."""
    t = np.asarray(t_ns, dtype=np.int64)
    if len(t) == 0:
        return Cleaned(np.zeros(0, np.int64), 0, 0)
    out_of_order = int(np.count_nonzero(np.diff(t) < 0))
    order = np.argsort(t, kind="stable")
    ts = t[order]
    first = np.ones(len(ts), dtype=bool)
    first[1:] = ts[1:] != ts[:-1]
    return Cleaned(order[first].astype(np.int64), out_of_order, int(np.count_nonzero(~first)))


@dataclass(frozen=True)
class Pairing:
    """Left/right frames matched by timestamp."""

    left: np.ndarray  # indices into the left times
    right: np.ndarray  # indices into the right times (same length)
    unmatched_left: int
    unmatched_right: int


def pair_stereo(left_t_ns: np.ndarray, right_t_ns: np.ndarray, tolerance_ns: int) -> Pairing:
    """Match each left time to the nearest right time within ``tolerance_ns`` (both increasing).

    A right frame is used at most once (the closest left frame wins).
    """
    lt = np.asarray(left_t_ns, dtype=np.int64)
    rt = np.asarray(right_t_ns, dtype=np.int64)
    if len(lt) == 0 or len(rt) == 0:
        return Pairing(np.zeros(0, np.int64), np.zeros(0, np.int64), len(lt), len(rt))
    j = np.searchsorted(rt, lt)
    lo = np.clip(j - 1, 0, len(rt) - 1)
    hi = np.clip(j, 0, len(rt) - 1)
    pick = np.where(np.abs(rt[lo] - lt) <= np.abs(rt[hi] - lt), lo, hi)
    dist = np.abs(rt[pick] - lt)
    ok = dist <= tolerance_ns
    li = np.nonzero(ok)[0]
    ri = pick[ok]
    # a right frame claimed twice: keep the closer claim
    if len(ri) and np.any(np.diff(ri) == 0):
        order = np.lexsort((dist[li], ri))
        li_s, ri_s = li[order], ri[order]
        first = np.ones(len(ri_s), dtype=bool)
        first[1:] = ri_s[1:] != ri_s[:-1]
        keep = np.sort(li_s[first])
        li = keep
        ri = pick[keep]
    return Pairing(li.astype(np.int64), ri.astype(np.int64), len(lt) - len(li), len(rt) - len(ri))


@dataclass(frozen=True)
class Gaps:
    """Intervals much longer than the nominal sampling period."""

    nominal_dt_ns: int
    starts_ns: np.ndarray  # time of the sample before each gap
    lengths_ns: np.ndarray

    def __len__(self) -> int:
        return len(self.starts_ns)

    def describe(self, what: str) -> str | None:
        if len(self) == 0:
            return None
        k = int(np.argmax(self.lengths_ns))
        return (
            f"{what}: {len(self)} gap(s) longer than {GAP_FACTOR:g}x the "
            f"{self.nominal_dt_ns * 1e-6:.2f} ms period; longest {self.lengths_ns[k] * 1e-6:.1f} ms "
            f"at t={self.starts_ns[k] * 1e-9:.3f} s; total {self.lengths_ns.sum() * 1e-9:.3f} s"
        )


GAP_FACTOR = 2.5


def find_gaps(t_ns: np.ndarray, factor: float = GAP_FACTOR) -> Gaps:
    """Intervals longer than ``factor`` x the median interval of an increasing series."""
    t = np.asarray(t_ns, dtype=np.int64)
    if len(t) < 3:
        return Gaps(0, np.zeros(0, np.int64), np.zeros(0, np.int64))
    dt = np.diff(t)
    nominal = int(np.median(dt))
    big = np.nonzero(dt > factor * nominal)[0]
    return Gaps(nominal, t[big], dt[big])


def rate_hz(t_ns: np.ndarray) -> float:
    """Median sampling rate of an increasing series (0 when fewer than two samples)."""
    t = np.asarray(t_ns, dtype=np.int64)
    if len(t) < 2:
        return 0.0
    dt = float(np.median(np.diff(t)))
    return 1e9 / dt if dt > 0 else 0.0

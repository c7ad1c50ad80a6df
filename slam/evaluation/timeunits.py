"""Time units of trajectory files, and spotting a file whose times are in another unit.

A TUM file holds seconds and an EuRoC csv nanoseconds, but files written by hand or by other
tools often put EuRoC's nanoseconds (1.4e18) in a TUM file, or milliseconds anywhere. Read as
seconds, such times either overflow int64 nanoseconds or land far from the reference's times.
:func:`mismatch_message` compares the time ranges of reference and estimate under each unit
the user could pass (``--ref-time-unit``/``--est-time-unit``) and names the one that makes
them agree.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from slam.core.errors import InputError

#: Units a time column may be in, and how many of each make a second.
PER_SECOND = {"s": 1, "ms": 1_000, "us": 1_000_000, "ns": 1_000_000_000}
UNITS = tuple(PER_SECOND)
UNIT_NAMES = {"s": "seconds", "ms": "milliseconds", "us": "microseconds", "ns": "nanoseconds"}
#: Decimal digits that turn a value in the unit into nanoseconds (12.5 ms -> 12_500_000 ns).
NS_DIGITS = {"s": 9, "ms": 6, "us": 3, "ns": 0}

#: A unit change is proposed when the ranges as read share less than this part of their union...
OVERLAP_AS_READ_MAX = 0.01
#: ...and share at least this part after the change.
OVERLAP_CHANGED_MIN = 0.5
#: Times beyond this many seconds do not fit in int64 nanoseconds (the year 2262).
MAX_SECONDS = (2**63 - 1) / 1e9


@dataclass(frozen=True)
class TimeSpan:
    """First and last time (seconds, as read in ``unit``) and the number of poses of one input.

    ``adjustable``: whether a time-unit option applies to the input (text files: yes; bag
    stamps carry their own unit).
    """

    first_s: float
    last_s: float
    count: int
    unit: str
    adjustable: bool = True

    def raw(self, value_s: float) -> float:
        """A time in seconds as the file writes it (in ``unit``)."""
        return value_s * PER_SECOND[self.unit]

    def as_unit(self, unit: str) -> TimeSpan:
        """The span if the file's numbers were in ``unit`` instead."""
        f = PER_SECOND[self.unit] / PER_SECOND[unit]
        return TimeSpan(self.first_s * f, self.last_s * f, self.count, unit, self.adjustable)

    @property
    def spacing_s(self) -> float:
        """Mean time between poses (0 for a single pose)."""
        return (self.last_s - self.first_s) / (self.count - 1) if self.count > 1 else 0.0


class TimeUnitError(InputError):
    """Times that cannot be in the unit they were read in: too large for int64 nanoseconds, or
    distinct decimals that fall in one nanosecond. Carries the span (for
    :func:`mismatch_message`) and ``what`` was wrong, without the option to pass."""

    def __init__(
        self, what: str, span: TimeSpan, flag: str = "--ref-time-unit or --est-time-unit"
    ) -> None:
        others = ", ".join(u for u in UNITS if u != span.unit)
        super().__init__(f"{what}; pass {flag} with the file's unit ({others})")
        self.what = what
        self.span = span


def check_unit(unit: str) -> str:
    if unit not in PER_SECOND:
        raise InputError(f"unknown time unit {unit!r}; choose one of {', '.join(UNITS)}")
    return unit


def overlap(a: TimeSpan, b: TimeSpan) -> float:
    """Length of the intersection of the two time ranges over the length of their union."""
    inter = min(a.last_s, b.last_s) - max(a.first_s, b.first_s)
    union = max(a.last_s, b.last_s) - min(a.first_s, b.first_s)
    if inter < 0 or union <= 0:
        return 1.0 if inter == 0 and union == 0 else 0.0
    return inter / union


def _spacing_gap(a: TimeSpan, b: TimeSpan) -> float:
    """How many factors of ten lie between the pose spacings (0: same rate)."""
    if a.spacing_s <= 0 or b.spacing_s <= 0:
        return 0.0
    return abs(math.log10(a.spacing_s / b.spacing_s))


def likely_unit(ref: TimeSpan, est: TimeSpan) -> tuple[str, str] | None:
    """``(role, unit)`` when one input's times are plainly in another unit, else None.

    Proposed only when the ranges as read hardly overlap, the changed unit makes them overlap
    well, the changed times fit in int64 nanoseconds, and the pose spacings get closer: a short
    estimate inside a long reference (both in seconds) is left alone. The estimate is preferred
    unless the reference's change fits clearly better (it is usually the odd file).
    """
    if overlap(ref, est) >= OVERLAP_AS_READ_MAX:
        return None
    gap = _spacing_gap(ref, est)
    best: tuple[float, str, str] | None = None
    for role, side in (("estimate", est), ("reference", ref)):
        if not side.adjustable:
            continue
        for unit in UNITS:
            if unit == side.unit:
                continue
            changed = side.as_unit(unit)
            if max(abs(changed.first_s), abs(changed.last_s)) > MAX_SECONDS:
                continue
            r, e = (ref, changed) if role == "estimate" else (changed, est)
            score = overlap(r, e)
            if score < OVERLAP_CHANGED_MIN or _spacing_gap(r, e) >= gap:
                continue
            if best is None or score > best[0] + 0.05:
                best = (score, role, unit)
    return None if best is None else (best[1], best[2])


def mismatch_message(ref: TimeSpan, est: TimeSpan, ref_name: str, est_name: str) -> str | None:
    """One line naming the unit an input's times are really in and the option to pass."""
    found = likely_unit(ref, est)
    if found is None:
        return None
    role, unit = found
    side, other = (est, ref) if role == "estimate" else (ref, est)
    name, other_role = (est_name, "reference") if role == "estimate" else (ref_name, "estimate")
    flag = "--est-time-unit" if role == "estimate" else "--ref-time-unit"
    return (
        f"{role} {name}: timestamps look like {UNIT_NAMES[unit]} (first "
        f"{side.raw(side.first_s):.5g}), not {UNIT_NAMES[side.unit]}, given the {other_role}'s "
        f"{other.first_s:.3f}..{other.last_s:.3f} s: pass {flag} {unit}"
    )

"""Allowed ranges and units of numeric config fields, kept in each field's metadata.

Every ``int``/``float`` field of every config dataclass nested under ``SlamConfig`` is declared
with :func:`bounded` (``tests/test_config_bounds.py`` fails on one that is not), and
``slam.config.validate_config`` checks them all on every loaded config before a run. This
module imports nothing else of the project, so every config module can use it.

A field's unit has one home: the end of its name (``_m``, ``_px``, ``_m_s2``: :data:`NAME_UNITS`)
or, when the name has none, ``bounded(..., unit=...)``; :func:`field_unit` reads either.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, TypeVar

T = TypeVar("T", int, float)

METADATA_KEY = "bounds"
UNIT_KEY = "unit"

NAME_UNITS: dict[str, str] = {
    "_m_per_sqrt_s": "m/sqrt(s)",
    "_rad_per_sqrt_s": "rad/sqrt(s)",
    "_deg_per_m": "deg/m",
    "_keyframes": "keyframes",
    "_frames": "frames",
    "_m_s2": "m/s^2",
    "_rad_s": "rad/s",
    "_m_s": "m/s",
    "_deg": "deg",
    "_rad": "rad",
    "_px": "px",
    "_ms": "ms",
    "_m": "m",
    "_s": "s",
}
"""Field-name endings that spell a unit (the longest matching ending wins)."""


@dataclass(frozen=True)
class Bounds:
    """The allowed range of one numeric config field (and optionally its order with another)."""

    lo: float
    """Smallest allowed value (exclusive when ``lo_open``)."""
    hi: float | None = None
    """Largest allowed value (exclusive when ``hi_open``); None: unbounded above."""
    lo_open: bool = False
    hi_open: bool = False
    below: str = ""
    """Name of a field of the same config this one must stay below (a min/max pair) ..."""
    below_or_equal: bool = False
    """... or equal to."""
    hint: str = ""
    """Appended to the error message (what to do instead)."""

    def contains(self, value: float) -> bool:
        if value < self.lo or (self.lo_open and value == self.lo):
            return False
        return self.hi is None or value < self.hi or (not self.hi_open and value == self.hi)

    def interval(self) -> str:
        """``[1, 5000]``, ``(0, inf)``: the range in interval notation."""
        left = "(" if self.lo_open else "["
        if self.hi is None:
            return f"{left}{self.lo}, inf)"
        return f"{left}{self.lo}, {self.hi}{')' if self.hi_open else ']'}"


def bounded(
    default: T,
    *,
    ge: float | None = None,
    gt: float | None = None,
    le: float | None = None,
    lt: float | None = None,
    lt_field: str = "",
    le_field: str = "",
    hint: str = "",
    unit: str = "",
) -> T:
    """A dataclass field with ``default`` and its allowed range in the field's metadata.

    Exactly one lower bound (``ge``: >=, ``gt``: >) and at most one upper bound (``le``, ``lt``;
    none: unbounded above). ``lt_field``/``le_field``: the value must also stay below (or at
    most) another field of the same config, e.g. a minimum below its maximum. ``unit``: only for
    a field whose name does not end in one (:data:`NAME_UNITS`).
    """
    if (ge is None) == (gt is None):
        raise TypeError("bounded() needs exactly one lower bound: ge= or gt=")
    if le is not None and lt is not None:
        raise TypeError("bounded() takes at most one upper bound: le= or lt=")
    if lt_field and le_field:
        raise TypeError("bounded() takes at most one of lt_field= and le_field=")
    lo = ge if ge is not None else gt
    assert lo is not None
    bounds = Bounds(
        lo=lo,
        hi=le if le is not None else lt,
        lo_open=gt is not None,
        hi_open=lt is not None,
        below=lt_field or le_field,
        below_or_equal=bool(le_field),
        hint=hint,
    )
    if not bounds.contains(default):
        raise ValueError(f"default {default!r} outside its bounds {bounds.interval()}")
    metadata: dict[str, Any] = {METADATA_KEY: bounds}
    if unit:
        metadata[UNIT_KEY] = unit
    return field(default=default, metadata=metadata)


def field_bounds(f: Any) -> Bounds | None:
    """The :class:`Bounds` of a ``dataclasses.Field``, or None when it has none."""
    b = f.metadata.get(METADATA_KEY)
    return b if isinstance(b, Bounds) else None


def name_unit(name: str) -> str:
    """The unit a field name ends in (``max_depth_m``: ``m``), or ``""``."""
    endings = [e for e in NAME_UNITS if name.endswith(e)]
    return NAME_UNITS[max(endings, key=len)] if endings else ""


def field_unit(f: Any) -> str:
    """The unit of a ``dataclasses.Field``: from its metadata, else its name; ``""`` for none."""
    return str(f.metadata.get(UNIT_KEY, "")) or name_unit(f.name)

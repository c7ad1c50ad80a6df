"""Latency summaries (count, p50/p90/p99/max in ms) for stats.json."""

from __future__ import annotations

import numpy as np


def latency_summary(values_ms: list[float]) -> dict[str, float]:
    """Count and p50/p90/p99/max of durations in ms (``{"count": 0}`` when there are none)."""
    if not values_ms:
        return {"count": 0}
    a = np.asarray(values_ms)
    return {
        "count": len(a),
        "p50_ms": float(np.percentile(a, 50)),
        "p90_ms": float(np.percentile(a, 90)),
        "p99_ms": float(np.percentile(a, 99)),
        "max_ms": float(a.max()),
    }

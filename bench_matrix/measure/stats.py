"""Latency statistics from raw per-iteration durations."""

from __future__ import annotations

import numpy as np


def latency_summary(durations_ns: np.ndarray) -> dict[str, float]:
    """mean, p50, p90, p99, std (sample), min in milliseconds, and n; percentiles by linear interpolation."""
    ms = np.asarray(durations_ns, dtype=np.float64) / 1e6
    if ms.size == 0:
        raise ValueError("no timed iterations")
    p50, p90, p99 = np.percentile(ms, [50, 90, 99])
    return {"mean": float(ms.mean()), "p50": float(p50), "p90": float(p90), "p99": float(p99),
            "std": float(ms.std(ddof=1)) if ms.size > 1 else 0.0, "min": float(ms.min()), "n": int(ms.size)}

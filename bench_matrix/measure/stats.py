"""Latency statistics from raw per-iteration durations: percentiles, the median's confidence interval, and the
compact form the raw durations are stored in."""

from __future__ import annotations

import zlib

import numpy as np

CONFIDENCE = 0.95  # of the median's interval
SAMPLES_DTYPE = "<f4"  # raw latencies are kept as little-endian float32 milliseconds, zlib-compressed


def latency_summary(durations_ns: np.ndarray) -> dict[str, float | list[float] | None]:
    """mean, p50, p90, p99, std (sample), min in milliseconds, and n; percentiles by linear interpolation;
    p50_ci: the median's 95 % interval [lo, hi] in ms and p50_ci_rel: (hi - lo) / p50 (None when n < 6)."""
    ms = np.asarray(durations_ns, dtype=np.float64) / 1e6
    if ms.size == 0:
        raise ValueError("no timed iterations")
    p50, p90, p99 = np.percentile(ms, [50, 90, 99])
    interval = median_interval(ms)
    return {"mean": float(ms.mean()), "p50": float(p50), "p90": float(p90), "p99": float(p99),
            "std": float(ms.std(ddof=1)) if ms.size > 1 else 0.0, "min": float(ms.min()), "n": int(ms.size),
            "p50_ci": list(interval) if interval else None,
            "p50_ci_rel": (interval[1] - interval[0]) / float(p50) if interval and p50 > 0 else None}


def median_ranks(n: int, confidence: float = CONFIDENCE) -> tuple[int, int] | None:
    """0-based ranks (lo, hi) of the median's distribution-free interval [x(k), x(n-k+1)], k the largest with
    1 - 2 P(X ≤ k-1) ≥ `confidence` (X ~ Binomial(n, 1/2)); None if [min, max] falls short (n < 6 at 95 %)."""
    if n < 1:
        return None
    half = np.arange(1, n // 2 + 1, dtype=np.float64)
    log_choose = np.concatenate(([0.0], np.cumsum(np.log((n - half + 1) / half))))  # log C(n, j), j <= n/2
    cdf = np.cumsum(np.exp(log_choose - n * np.log(2.0)))  # P(X <= j), X: samples below the median
    k = int(np.searchsorted(cdf, (1 - confidence) / 2, side="right"))  # count of j with P(X <= j) <= alpha/2
    return None if k == 0 else (k - 1, n - k)  # [x(k), x(n-k+1)] (1-based) as 0-based ranks


def median_interval(values: np.ndarray, confidence: float = CONFIDENCE) -> tuple[float, float] | None:
    """The median's distribution-free `confidence` interval (order statistics, see median_ranks), or None."""
    ranks = median_ranks(len(values), confidence)
    if ranks is None:
        return None
    lo, hi = np.partition(np.asarray(values), ranks)[list(ranks)]
    return float(lo), float(hi)


def pack_samples(durations_ns: np.ndarray) -> bytes:
    """Raw durations as zlib-compressed little-endian float32 milliseconds."""
    return zlib.compress(np.asarray(np.asarray(durations_ns) / 1e6, dtype=SAMPLES_DTYPE).tobytes(), 6)


def unpack_samples(blob: bytes) -> np.ndarray:
    """The float32 milliseconds `pack_samples` stored."""
    return np.frombuffer(zlib.decompress(blob), dtype=SAMPLES_DTYPE)

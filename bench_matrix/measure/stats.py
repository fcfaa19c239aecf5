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


def accuracy(pred: np.ndarray, labels: np.ndarray, reference: np.ndarray | None) -> dict[str, object]:
    """mse/mae against labels (overall and per output) and max |difference| against the fp32 baseline."""
    pred = np.asarray(pred, np.float64).reshape(len(labels), -1)
    labels = np.asarray(labels, np.float64).reshape(len(labels), -1)
    if pred.shape != labels.shape:
        raise ValueError(f"model outputs have shape {pred.shape[1:]} per sample but labels have {labels.shape[1:]}")
    err = pred - labels
    out: dict[str, object] = {"mse": float(np.mean(err ** 2)), "mae": float(np.mean(np.abs(err))),
                              "mse_per_output": [float(v) for v in np.mean(err ** 2, axis=0)]}
    if reference is not None:
        ref = np.asarray(reference, np.float64).reshape(pred.shape)
        out["max_abs_diff_vs_baseline"] = float(np.max(np.abs(pred - ref)))
    return out

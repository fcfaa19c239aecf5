"""Timing loops: warm-up, then per-iteration perf_counter_ns until both a count and a duration are reached."""

from __future__ import annotations

import gc
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np


@dataclass(frozen=True)
class LoopSettings:
    """Warm-up and measuring budgets (iterations and seconds: both minimums must be met)."""

    warmup_iterations: int
    warmup_s: float
    min_iterations: int
    min_time_s: float
    max_time_s: float


def time_calls(call: Callable[[Any], Any], inputs: list[Any], settings: LoopSettings) -> np.ndarray:
    """Durations in ns of `call(inputs[i % len])`; the call itself must return only when the work is done."""
    clock = time.perf_counter_ns
    n_inputs = len(inputs)
    i = 0
    start = clock()
    while i < settings.warmup_iterations or clock() - start < settings.warmup_s * 1e9:
        call(inputs[i % n_inputs])
        i += 1
    durations: list[int] = []
    min_ns, max_ns = settings.min_time_s * 1e9, settings.max_time_s * 1e9
    gc_was_enabled = gc.isenabled()
    gc.disable()  # a collection inside a timed call is harness noise, not model latency
    try:
        begin = clock()
        i = 0
        while True:
            x = inputs[i % n_inputs]
            t0 = clock()
            call(x)
            t1 = clock()
            durations.append(t1 - t0)
            i += 1
            elapsed = t1 - begin
            if (i >= settings.min_iterations and elapsed >= min_ns) or elapsed >= max_ns:
                break
    finally:
        if gc_was_enabled:
            gc.enable()
    return np.asarray(durations, dtype=np.int64)


def drift(durations_ns: np.ndarray, chunks: int = 5) -> float:
    """Spread of the medians of consecutive chunks, relative to the overall median (0 = steady)."""
    parts = np.array_split(np.asarray(durations_ns, dtype=np.float64), chunks)
    medians = [float(np.median(p)) for p in parts if len(p)]
    return (max(medians) - min(medians)) / float(np.median(durations_ns))


def steady_time_calls(call: Callable[[Any], Any], inputs: list[Any], settings: LoopSettings,
                      tolerance: float = 0.05, attempts: int = 3) -> tuple[np.ndarray, dict[str, float]]:
    """time_calls, repeated while the chunk medians drift by more than `tolerance`; keep the steadiest."""
    best: tuple[float, np.ndarray] | None = None
    for attempt in range(1, attempts + 1):
        durations = time_calls(call, inputs, settings)
        spread = drift(durations)
        if best is None or spread < best[0]:
            best = (spread, durations)
        if spread <= tolerance:
            break
    assert best is not None
    return best[1], {"latency_stability": round(best[0], 4), "latency_attempts": attempt}


def throughput(call: Callable[[Any], Any], batch: Any, batch_size: int, seconds: float) -> dict[str, float]:
    """Samples per second at `batch_size`: two warm-up batches, then at least 3 batches and `seconds`."""
    for _ in range(2):
        call(batch)
    clock = time.perf_counter_ns
    n, begin = 0, clock()
    while n < 3 or clock() - begin < seconds * 1e9:
        call(batch)
        n += 1
    elapsed = (clock() - begin) / 1e9
    return {"throughput_sps": batch_size * n / elapsed, "throughput_batches": n}

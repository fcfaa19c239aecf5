"""Timing loops: warm-up, then per-iteration perf_counter_ns until a count and a duration are reached; a
round's short window of one cell (docs/metrics.md §5)."""

from __future__ import annotations

import gc
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from bench_matrix.measure.interference import Sampler

Clock = Callable[[], int]  # nanoseconds, like time.perf_counter_ns
WINDOW_WARMUP = 2  # untimed calls before each window (and WINDOW_WARMUP_SHARE of its length at least)
WINDOW_WARMUP_SHARE = 0.05


@dataclass(frozen=True)
class LoopSettings:
    """Warm-up and measuring budgets: iterations and seconds, both minimums met, the loop stops at
    `max_time_s` in any case."""

    warmup_iterations: int
    warmup_s: float
    min_iterations: int
    min_time_s: float
    max_time_s: float


def time_calls(call: Callable[[Any], Any], inputs: list[Any], settings: LoopSettings,
               sampler: Sampler | None = None, clock: Clock = time.perf_counter_ns) -> np.ndarray:
    """Durations in ns of `call(inputs[i % len])` (the call must return only when the work is done); `sampler`
    is started after the warm-up."""
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
        if sampler is not None:
            sampler.start()
        begin = clock()
        while True:
            x = inputs[len(durations) % n_inputs]
            t0 = clock()
            call(x)
            t1 = clock()
            durations.append(t1 - t0)
            elapsed = t1 - begin
            if elapsed >= max_ns or (len(durations) >= settings.min_iterations and elapsed >= min_ns):
                break
    finally:
        if gc_was_enabled:
            gc.enable()
    return np.asarray(durations, dtype=np.int64)


def latency_window(call: Callable[[Any], Any], inputs: list[Any], seconds: float,
                   sampler: Sampler | None = None, clock: Clock = time.perf_counter_ns,
                   warmup: int = WINDOW_WARMUP) -> np.ndarray:
    """One round's window: a short warm-up (`warmup` calls, and WINDOW_WARMUP_SHARE of the window at least),
    then durations in ns of calls until `seconds` have passed (at least one call)."""
    window = LoopSettings(warmup, seconds * WINDOW_WARMUP_SHARE, 1, seconds, seconds)
    return time_calls(call, inputs, window, sampler, clock)


def throughput(call: Callable[[Any], Any], batch: Any, batch_size: int, seconds: float,
               sampler: Sampler | None = None, clock: Clock = time.perf_counter_ns) -> dict[str, Any]:
    """Samples per second at `batch_size`: two warm-up batches, then at least 3 batches and `seconds`; with
    each batch's duration in ns ("batch_ns", raw samples kept for `compare`, not a metric)."""
    for _ in range(2):
        call(batch)
    if sampler is not None:
        sampler.start()
    stamps = [clock()]
    while len(stamps) < 4 or stamps[-1] - stamps[0] < seconds * 1e9:
        call(batch)
        stamps.append(clock())
    n, elapsed = len(stamps) - 1, (stamps[-1] - stamps[0]) / 1e9
    return {"throughput_sps": batch_size * n / elapsed, "throughput_batches": n, "batch_ns": np.diff(stamps)}

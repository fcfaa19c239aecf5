"""Timing loops: warm-up, then per-iteration perf_counter_ns until a count and a duration are reached (and
the median's confidence interval is narrow); each timed phase repeated while it was disturbed."""

from __future__ import annotations

import gc
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass
from typing import Any, Generic, TypeVar

import numpy as np

from bench_matrix.measure.interference import Interference, Limits, Sampler
from bench_matrix.measure.stats import relative_width

T = TypeVar("T")
Clock = Callable[[], int]  # nanoseconds, like time.perf_counter_ns
DRIFT_LIMIT = 0.05  # chunk medians of one window may differ by this fraction of the overall median
ATTEMPTS = 3  # timed windows per phase at most: the first, then re-measurements of an unclean one
RETRY_PAUSE_S = 0.5  # before re-measuring a disturbed window, n times this (n-th retry): load may pass


@dataclass(frozen=True)
class Instruments:
    """What a timed phase reads and waits with: a clock in ns, a new interference sampler for each attempt
    and the pause before re-measuring; tests pass scripted ones."""

    clock: Clock = time.perf_counter_ns
    samplers: Callable[[], Sampler] = Sampler
    sleep: Callable[[float], None] = time.sleep


REAL = Instruments()  # the machine's: what every production caller uses


@dataclass(frozen=True)
class LoopSettings:
    """Warm-up and measuring budgets (iterations and seconds: both minimums must be met), and the early stop:
    once they are, the loop ends when the median's 95 % interval spans at most `ci_rel_width` of it
    (None: at once)."""

    warmup_iterations: int
    warmup_s: float
    min_iterations: int
    min_time_s: float
    max_time_s: float
    ci_rel_width: float | None = None


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
    next_check = settings.min_iterations
    gc_was_enabled = gc.isenabled()
    gc.disable()  # a collection inside a timed call is harness noise, not model latency
    try:
        if sampler is not None:
            sampler.start()
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
            if elapsed >= max_ns:
                break
            if i >= next_check and elapsed >= min_ns:
                if _narrow(durations, settings.ci_rel_width):
                    break
                next_check = i + max(i // 10, 1)  # look again after 10 % more calls: linear total cost
    finally:
        if gc_was_enabled:
            gc.enable()
    return np.asarray(durations, dtype=np.int64)


def _narrow(durations: list[int], ci_rel_width: float | None) -> bool:
    """Whether the early stop allows ending the loop now."""
    if ci_rel_width is None:
        return True
    width = relative_width(np.asarray(durations, dtype=np.float64))
    return width is not None and width <= ci_rel_width


def drift(durations_ns: np.ndarray, chunks: int = 5) -> float:
    """Spread of the medians of consecutive chunks, relative to the overall median (0 = steady)."""
    parts = np.array_split(np.asarray(durations_ns, dtype=np.float64), chunks)
    medians = [float(np.median(p)) for p in parts if len(p)]
    return (max(medians) - min(medians)) / float(np.median(durations_ns))


@dataclass(frozen=True)
class Attempt(Generic[T]):
    """One timed window: its result and headline figures, the interference during it, and what was wrong:
    `disturbed` (interference above the limits) and `unsteady` (the phase's own check, e.g. drift)."""

    result: T
    figures: dict[str, float]
    interference: Interference
    disturbed: str | None
    unsteady: str | None

    @property
    def clean(self) -> bool:
        return self.disturbed is None and self.unsteady is None

    def as_dict(self) -> dict[str, Any]:
        return {**self.figures, **self.interference.as_dict(), "disturbed": self.disturbed,
                "unsteady": self.unsteady}


@dataclass(frozen=True)
class Phase(Generic[T]):
    """The attempts of one timed phase and the one kept: the first clean one, else the best of the rest."""

    attempts: tuple[Attempt[T], ...]
    kept: int

    @property
    def result(self) -> T:
        return self.attempts[self.kept].result

    @property
    def disturbed(self) -> str | None:
        """Why the kept attempt counts as disturbed (then every attempt did), or None."""
        return self.attempts[self.kept].disturbed

    def as_dict(self) -> dict[str, Any]:
        return {"attempts": [a.as_dict() for a in self.attempts], "kept": self.kept}


def until_clean(measure: Callable[[Sampler], T], unsteady: Callable[[T], str | None],
                figures: Callable[[T], dict[str, float]], cost: Callable[[T], float], limits: Limits,
                attempts: int = ATTEMPTS, instruments: Instruments = REAL) -> Phase[T]:
    """Run `measure` (which starts the sampler where its timing begins) until an attempt is neither
    disturbed under `limits` nor `unsteady`; after `attempts` such ones, keep the undisturbed one of lowest
    `cost` (any of lowest `cost` if all were disturbed)."""
    tries: list[Attempt[T]] = []
    for number in range(attempts):
        if tries and tries[-1].disturbed:  # other work may pass; drift is as often the runtime's own
            instruments.sleep(RETRY_PAUSE_S * number)
        sampler = instruments.samplers()
        result = measure(sampler)
        interference = sampler.stop()
        tries.append(Attempt(result, figures(result), interference, interference.problem(limits),
                             unsteady(result)))
        if tries[-1].clean:
            return Phase(tuple(tries), len(tries) - 1)
    return Phase(tuple(tries), min(range(len(tries)),
                                   key=lambda i: (tries[i].disturbed is not None, cost(tries[i].result))))


def steady_time_calls(call: Callable[[Any], Any], inputs: list[Any], settings: LoopSettings, limits: Limits,
                      attempts: int = ATTEMPTS, instruments: Instruments = REAL) -> Phase[np.ndarray]:
    """time_calls, repeated while a window was disturbed or drifted (chunk medians more than DRIFT_LIMIT
    apart); when every attempt was, the one with the lowest median is kept (interference only adds time)."""
    def drifted(durations: np.ndarray) -> str | None:
        spread = drift(durations)
        if spread <= DRIFT_LIMIT:
            return None
        return f"chunk medians drifted by {spread:.0%} (limit {DRIFT_LIMIT:.0%})"

    def measure(sampler: Sampler) -> np.ndarray:
        return time_calls(call, inputs, settings, sampler, instruments.clock)

    return until_clean(measure, drifted, _latency_figures, lambda durations: float(np.median(durations)),
                       limits, attempts, instruments)


def _latency_figures(durations_ns: np.ndarray) -> dict[str, float]:
    """What an attempt's latency was: p50 and p99 in ms, and n."""
    p50, p99 = np.percentile(np.asarray(durations_ns, dtype=np.float64) / 1e6, [50, 99])
    return {"p50_ms": round(float(p50), 6), "p99_ms": round(float(p99), 6), "n": int(len(durations_ns))}


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


def steady_throughput(call: Callable[[Any], Any], batch: Any, batch_size: int, seconds: float, limits: Limits,
                      attempts: int = ATTEMPTS, instruments: Instruments = REAL) -> Phase[dict[str, float]]:
    """throughput, repeated while disturbed; when every attempt was, the fastest is kept."""
    def measure(sampler: Sampler) -> dict[str, Any]:
        return throughput(call, batch, batch_size, seconds, sampler, instruments.clock)

    return until_clean(measure, lambda _: None, lambda rate: {"throughput_sps": rate["throughput_sps"]},
                       lambda rate: -rate["throughput_sps"], limits, attempts, instruments)


def interference_record(phases: dict[str, Phase[Any]], limits: Limits) -> dict[str, Any]:
    """metrics["interference"]: flagged when some phase stayed disturbed through every attempt, the reason,
    the limits and every attempt's figures by phase."""
    reasons = [f"{name}: {phase.disturbed}" for name, phase in phases.items() if phase.disturbed]
    return {"flagged": bool(reasons), "reason": " | ".join(reasons) or None, "limits": asdict(limits),
            "phases": {name: phase.as_dict() for name, phase in phases.items()}}

"""A cell's stream, in its measure job's process: frames arrive on the harness's clock (frame k at t0 + k ×
period, due by the next frame's arrival) and the loaded session serves them, skipping or queueing those that
arrive while a call runs; the figures and per-call series go into the cell's record (docs/stream.md)."""

from __future__ import annotations

import gc
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from bench_matrix import data
from bench_matrix.measure.stats import pack_samples
from bench_matrix.phases import phase
from bench_matrix.scenarios.base import Loaded, Outcome
from bench_matrix.scenarios.stream import StreamPlan
from bench_matrix.tensors import bind, take

INPUTS = 16  # batch-1 test inputs prepared before the clock starts, served in turn
WARMUP_CALLS = 8  # untimed calls right before the stream (the session was warmed up for the latency windows)
BEHIND_LIMIT = 2  # a queue fallen behind is cut at this many times the stream's duration: the rest dropped
SPIN_NS = 500_000  # the last half millisecond before a frame's arrival is waited by spinning, not sleeping


class Clock:
    """The stream's clock: nanoseconds from perf_counter_ns, and a precise wait (sleep, then spin)."""

    def now(self) -> int:
        return time.perf_counter_ns()

    def wait_until(self, t_ns: int) -> None:
        wait_until(t_ns, self.now, time.sleep)


def wait_until(t_ns: int, now: Callable[[], int], sleep: Callable[[float], Any]) -> None:
    """Return at `t_ns` (at once when it has passed): sleep until SPIN_NS before it, then spin."""
    while (left := t_ns - now()) > 0:
        if left > SPIN_NS:
            sleep((left - SPIN_NS) / 1e9)


@dataclass(frozen=True)
class Timeline:
    """A stream as it ran: per completed call, its frame's arrival, its start and its end (ns)."""

    t0: int
    period_ns: int
    frames: int
    arrivals: np.ndarray
    starts: np.ndarray
    ends: np.ndarray


def serve(call: Callable[[Any], Any], inputs: list[Any], frames: int, period_ns: int, policy: str,
          clock: Clock) -> Timeline:
    """Serve `frames` frames, one every `period_ns`, each the next of `inputs`, GC off: `queue` serves each in
    turn (up to BEHIND_LIMIT × the stream's duration), `skip` drops frames arriving during a call."""
    done: list[tuple[int, int, int]] = []
    gc_was_enabled = gc.isenabled()
    gc.disable()
    try:
        t0, k = clock.now(), 0
        while k < frames and clock.now() - t0 < BEHIND_LIMIT * frames * period_ns:
            arrival = t0 + k * period_ns
            clock.wait_until(arrival)
            start = clock.now()
            call(inputs[len(done) % len(inputs)])
            end = clock.now()
            done.append((arrival, start, end))
            k = k + 1 if policy == "queue" else max(k + 1, -(-(end - t0) // period_ns))
    finally:
        if gc_was_enabled:
            gc.enable()
    arrivals, starts, ends = (np.asarray(column, dtype=np.int64) for column in zip(*done))
    return Timeline(t0, period_ns, frames, arrivals, starts, ends)


def figures(timeline: Timeline) -> dict[str, Any]:
    """The stream's figures (docs/stream.md defines each): counts, shares, rate, jitter and latency in ms."""
    period, ends = timeline.period_ns, timeline.ends
    completed = len(ends)
    missed = int(np.sum(ends > timeline.arrivals + period))
    span_ns = max(timeline.frames * period, int(ends[-1]) - timeline.t0)
    jitter = np.abs(np.diff(ends) - period)
    found = {"frames": timeline.frames, "completed": completed, "achieved_hz": completed / span_ns * 1e9,
             "missed": missed, "miss_share": missed / completed, "dropped": timeline.frames - completed,
             "drop_share": (timeline.frames - completed) / timeline.frames,
             **_percentiles("jitter", jitter), **_percentiles("latency", ends - timeline.starts),
             **_percentiles("e2e", ends - timeline.arrivals)}
    return {k: _finite(v) for k, v in found.items()}


def _percentiles(name: str, durations_ns: np.ndarray) -> dict[str, float | None]:
    """`name`_p50_ms and `name`_p99_ms (linear interpolation); None without a sample."""
    if not durations_ns.size:
        return {f"{name}_p50_ms": None, f"{name}_p99_ms": None}
    p50, p99 = np.percentile(durations_ns / 1e6, [50, 99])
    return {f"{name}_p50_ms": float(p50), f"{name}_p99_ms": float(p99)}


def _finite(value: Any) -> Any:
    """Counts as they are, figures rounded to 6 decimals; NaN or Inf as None (never stored)."""
    if isinstance(value, float):
        return round(value, 6) if np.isfinite(value) else None
    return value


def run_stream(loaded: Loaded, plan: StreamPlan) -> Outcome:
    """The record's `stream` field (the settings and the figures) and the calls' service and end-to-end
    times as raw series (`stream_latency_ms`, `stream_e2e_ms`)."""
    spec, session = plan.spec, loaded.session
    inputs = [session.prepare(host) for host in _hosts(loaded)]
    for i in range(WARMUP_CALLS):
        session.execute(inputs[i % len(inputs)])
    phase(f"stream · {spec.rate_hz:g} Hz · {spec.policy}")
    timeline = serve(session.execute, inputs, spec.frames, round(1e9 / spec.rate_hz), spec.policy, Clock())
    samples = {"stream_latency_ms": pack_samples(timeline.ends - timeline.starts),
               "stream_e2e_ms": pack_samples(timeline.ends - timeline.arrivals)}
    return Outcome({"stream": {**spec.stream_dict(), **figures(timeline)}}, samples)


def _hosts(loaded: Loaded) -> list[dict[str, np.ndarray]]:
    """Up to INPUTS test samples at batch 1, bound to the model's inputs."""
    job = loaded.job
    few, _ = data.load_split(job.data.directory, "test", job.data.preprocess, job.layout, INPUTS)
    few = bind(few, job.source.inputs)
    return [take(few, slice(i, i + 1)) for i in range(min(INPUTS, len(next(iter(few.values())))))]

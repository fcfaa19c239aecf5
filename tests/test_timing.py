"""The timing loops and a round's window, driven by a fake clock that only a call moves and by scripted
samplers: every figure is exact, none depends on the machine's load."""

from __future__ import annotations

import time
from collections.abc import Iterable

import numpy as np
import pytest

from bench_matrix.measure.interference import Interference
from bench_matrix.measure.timing import WINDOW_WARMUP, LoopSettings, latency_window, time_calls

MS = 1_000_000  # ns
QUIET = Interference(wall_s=1.0, cpus=(1,), own_cpu_s=1.0, other_cpu_s=0.0, other_share=0.0,
                     machine_share=0.0, steal_share=0.0, preemptions=3, cpu_busy={0: 0.0, 1: 1.0})


class Bench:
    """A fake machine: a clock in ns that stands still except while a call runs (each call takes the next
    scripted duration), samplers that report the next scripted interference, and the pauses asked for."""

    def __init__(self, durations_ns: Iterable[int], interference: Iterable[Interference] = ()) -> None:
        self.now = 0
        self.durations = iter(durations_ns)
        self.interference = iter(interference)
        self.log: list[str] = []  # the calls' inputs, and "start" and "stop" of each sampler, in order

    def clock(self) -> int:
        return self.now

    def call(self, x: str) -> None:
        self.log.append(x)
        self.now += next(self.durations)

    def sampler(self) -> ScriptedSampler:
        return ScriptedSampler(next(self.interference, QUIET), self.log)


class ScriptedSampler:
    """A sampler whose stop() reports the interference it was given."""

    def __init__(self, seen: Interference, log: list[str]) -> None:
        self.seen, self.log = seen, log

    def start(self) -> None:
        self.log.append("start")

    def stop(self) -> Interference:
        self.log.append("stop")
        return self.seen


def ms(*durations: float) -> list[int]:
    return [round(d * MS) for d in durations]


@pytest.mark.parametrize("warmup, minimums, warm, timed", [
    ((3, 0.0), (10, 0.05), 3, 50),  # 10 calls are 10 ms: the time minimum decides
    ((2, 0.005), (30, 0.01), 5, 30),  # 5 warm-up calls fill 5 ms; 30 timed calls outlast 10 ms
])
def test_time_calls_meets_both_minimums(warmup, minimums, warm, timed):
    bench = Bench(ms(1) * 1000)
    settings = LoopSettings(*warmup, *minimums, max_time_s=5)
    durations = time_calls(bench.call, ["a", "b"], settings, clock=bench.clock)
    assert durations.dtype == np.int64 and durations.tolist() == ms(1) * timed
    assert bench.log == (["a", "b"] * warm)[:warm] + ["a", "b"] * (timed // 2)  # cycled; again from the first


def test_time_calls_starts_its_sampler_after_the_warm_up():
    bench = Bench(ms(1) * 100)
    time_calls(bench.call, ["x"], LoopSettings(4, 0.0, 6, 0.0, 5), bench.sampler(), bench.clock)
    assert bench.log == ["x"] * 4 + ["start"] + ["x"] * 6  # stopping it is the caller's


def test_time_calls_stops_at_max_time():
    bench = Bench(ms(5) * 1000)
    settings = LoopSettings(0, 0.0, min_iterations=10_000, min_time_s=0.0, max_time_s=0.05)
    assert time_calls(bench.call, [None], settings, clock=bench.clock).tolist() == ms(5) * 10


def test_a_window_warms_up_briefly_then_times_calls_for_its_length():
    bench = Bench(ms(1) * 1000)
    durations = latency_window(bench.call, ["a", "b"], 0.04, bench.sampler(), bench.clock)
    assert durations.tolist() == ms(1) * 40  # 40 calls of 1 ms fill the 40 ms window
    warm = 2  # WINDOW_WARMUP calls, and 5 % of the window (2 ms) at least
    assert WINDOW_WARMUP == 2 and bench.log[:warm + 1] == ["a", "b", "start"]


def test_a_window_of_a_call_longer_than_it_times_that_one_call():
    bench = Bench(ms(300) * 10)
    assert latency_window(bench.call, [None], 0.05, None, bench.clock).tolist() == ms(300)


def test_on_the_real_clock_each_call_is_timed_whole():
    calls = []
    settings = LoopSettings(3, 0.0, min_iterations=10, min_time_s=0.02, max_time_s=5)
    durations = time_calls(lambda x: (calls.append(x), time.sleep(0.001)), ["a", "b"], settings)
    assert len(durations) >= 10 and len(calls) == len(durations) + 3  # however loaded the machine is
    assert np.all(durations >= MS)  # each timed call slept at least 1 ms: more under load, never less
    window = latency_window(lambda x: time.sleep(0.01), [None], 0.05)
    assert len(window) >= 1 and np.all(window >= 10 * MS) and window.sum() >= 0.05 * 1e9 - 10 * MS

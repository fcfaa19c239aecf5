"""The timing loops and their re-measuring decisions, driven by a fake clock that only a call moves and by
samplers that report scripted interference: every figure is exact, none depends on the machine's load."""

from __future__ import annotations

import time
from collections.abc import Iterable
from dataclasses import replace

import numpy as np
import pytest

from bench_matrix.measure.interference import Interference, Limits, Sampler
from bench_matrix.measure.timing import (
    ATTEMPTS,
    REAL,
    Instruments,
    LoopSettings,
    drift,
    interference_record,
    steady_throughput,
    steady_time_calls,
    throughput,
    time_calls,
)

MS = 1_000_000  # ns
QUIET = Interference(wall_s=1.0, cpus=(1,), own_cpu_s=1.0, other_cpu_s=0.0, other_share=0.0,
                     machine_share=0.0, steal_share=0.0, preemptions=3, cpu_busy={0: 0.0, 1: 1.0})
BUSY = replace(QUIET, own_cpu_s=0.6, other_cpu_s=0.4, other_share=0.4, machine_share=0.2)  # a competitor
BUSY_WHY = "other processes took 40% of the measuring CPU(s) (limit 5%)"
EXACTLY = LoopSettings(0, 0.0, min_iterations=20, min_time_s=0.0, max_time_s=5)  # 20 timed calls per attempt


class Bench:
    """A fake machine: a clock in ns that stands still except while a call runs (each call takes the next
    scripted duration), samplers that report the next scripted interference, and the pauses asked for."""

    def __init__(self, durations_ns: Iterable[int], interference: Iterable[Interference] = ()) -> None:
        self.now = 0
        self.durations = iter(durations_ns)
        self.interference = iter(interference)
        self.pauses: list[float] = []
        self.log: list[str] = []  # the calls' inputs, and "start" and "stop" of each sampler, in order
        self.instruments = Instruments(clock=self.clock, samplers=self.sampler, sleep=self.pauses.append)

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


def test_time_calls_goes_on_until_the_median_interval_is_narrow():
    wide = LoopSettings(0, 0.0, min_iterations=20, min_time_s=0.0, max_time_s=0.3, ci_rel_width=0.05)
    bench = Bench(ms(0.5, 3) * 1000)  # two modes: the median's interval always spans both
    timed = time_calls(bench.call, [None], wide, clock=bench.clock)
    assert len(timed) == 172 and timed.sum() == ms(301)[0]  # 85 pairs are 297.5 ms; 2 calls more reach 0.3 s
    settling = Bench(ms(0.5, 3) * 10 + ms(1) * 1000)  # wide for 20 calls, then steady at 1 ms
    # looked at after 20 calls, then after every 10 % more: 22, 24, 26, 28, 30 (the interval's lower end is
    # still the 10th call of 0.5 ms), 33 (both of its ends are 1 ms calls: narrow)
    assert len(time_calls(settling.call, [None], wide, clock=settling.clock)) == 33
    steady = Bench(ms(1) * 1000)
    loose = replace(wide, ci_rel_width=1.0)
    assert len(time_calls(steady.call, [None], loose, clock=steady.clock)) == 20  # narrow at the first look


def test_throughput_counts_samples_per_second():
    bench = Bench(ms(10) * 100)
    out = throughput(bench.call, "batch", 8, seconds=0.1, sampler=bench.sampler(), clock=bench.clock)
    assert out["throughput_batches"] == 10 and out["throughput_sps"] == pytest.approx(8 * 10 / 0.1)
    assert out["batch_ns"].tolist() == ms(10) * 10
    assert bench.log == ["batch"] * 2 + ["start"] + ["batch"] * 10
    short = Bench(ms(10) * 100)
    assert throughput(short.call, None, 8, 0.0, clock=short.clock)["throughput_batches"] == 3  # at least 3


def test_drift_is_zero_for_steady_and_large_for_a_step():
    assert drift(np.full(100, MS)) == 0.0
    step = np.concatenate([np.full(50, MS), np.full(50, 1.5 * MS)])  # interference half-way
    assert drift(step) == pytest.approx(0.5 / 1.25)


def test_steady_time_calls_repeats_a_drifting_measurement_and_keeps_the_clean_one():
    bench = Bench(ms(1) * 4 + ms(4) * 4 + ms(1) * 12 + ms(1) * 20)  # a slow spell in the second fifth
    phase = steady_time_calls(bench.call, ["x"], EXACTLY, Limits(), instruments=bench.instruments)
    assert len(phase.attempts) == 2 and phase.kept == 1 and phase.attempts[1].clean
    first = phase.attempts[0]
    assert first.unsteady == "chunk medians drifted by 300% (limit 5%)" and first.disturbed is None
    assert phase.result.tolist() == ms(1) * 20 and phase.disturbed is None
    assert bench.pauses == []  # drift is as often the runtime's own: no pause for it
    assert bench.log == (["start"] + ["x"] * 20 + ["stop"]) * 2


def test_a_disturbed_window_is_measured_again_after_a_pause_and_the_clean_one_kept():
    bench = Bench(ms(2) * 20 + ms(1) * 20, [BUSY, QUIET])
    phase = steady_time_calls(bench.call, [None], EXACTLY, Limits(), instruments=bench.instruments)
    assert [a.disturbed for a in phase.attempts] == [BUSY_WHY, None] and phase.kept == 1
    assert bench.pauses == [0.5]
    assert interference_record({"latency": phase}, Limits())["flagged"] is False


def test_a_phase_disturbed_in_every_attempt_keeps_the_lowest_median_and_says_why():
    bench = Bench(ms(3) * 20 + ms(1) * 20 + ms(2) * 20, [BUSY] * 3)  # the second attempt the fastest
    phase = steady_time_calls(bench.call, [None], EXACTLY, Limits(), instruments=bench.instruments)
    assert len(phase.attempts) == ATTEMPTS and phase.kept == 1 and phase.result.tolist() == ms(1) * 20
    assert phase.disturbed == BUSY_WHY and bench.pauses == [0.5, 1.0]  # longer each time: load may pass
    record = interference_record({"latency": phase}, Limits())
    assert record["flagged"] is True and record["reason"] == f"latency: {BUSY_WHY}"
    assert record["limits"] == {"other_share": 0.05, "machine_share": 0.25, "steal_share": 0.03}
    latency = record["phases"]["latency"]
    assert latency["kept"] == 1 and [a["p50_ms"] for a in latency["attempts"]] == [3.0, 1.0, 2.0]
    assert latency["attempts"][0] == {"p50_ms": 3.0, "p99_ms": 3.0, "n": 20, **BUSY.as_dict(),
                                      "disturbed": BUSY_WHY, "unsteady": None}


def test_drift_alone_re_measures_but_never_flags():
    bench = Bench(ms(2) * 10 + ms(6) * 10 + ms(1) * 10 + ms(3) * 10 + ms(3) * 10 + ms(9) * 10)  # each slows
    phase = steady_time_calls(bench.call, [None], EXACTLY, Limits(), instruments=bench.instruments)
    assert len(phase.attempts) == ATTEMPTS and all(a.unsteady and a.disturbed is None for a in phase.attempts)
    assert phase.kept == 1 and phase.disturbed is None and bench.pauses == []  # the lowest median: 2 ms
    assert interference_record({"latency": phase}, Limits())["flagged"] is False


def test_an_undisturbed_attempt_is_kept_over_a_faster_disturbed_one():
    bench = Bench(ms(1) * 20 + ms(2) * 10 + ms(6) * 10 + ms(1.5) * 20, [BUSY, QUIET, BUSY])
    phase = steady_time_calls(bench.call, [None], EXACTLY, Limits(), instruments=bench.instruments)
    assert phase.kept == 1 and phase.attempts[1].unsteady and phase.disturbed is None  # others only add time
    assert bench.pauses == [0.5]  # after the disturbed first attempt, not after the drifting second


def test_throughput_is_measured_again_while_disturbed_and_the_fastest_kept_without_a_drift_check():
    per_attempt = [ms(10) * 5, ms(5) * 5, ms(8) * 5]  # 2 warm-up batches and 3 timed ones each
    bench = Bench(sum(per_attempt, []), [BUSY] * 3)
    phase = steady_throughput(bench.call, None, 8, 0.0, Limits(), instruments=bench.instruments)
    assert [a.figures["throughput_sps"] for a in phase.attempts] == pytest.approx([800, 1600, 1000])
    assert phase.kept == 1 and phase.disturbed == BUSY_WHY and bench.pauses == [0.5, 1.0]
    uneven = Bench(ms(1, 1, 1, 50, 1))
    once = steady_throughput(uneven.call, None, 8, 0.0, Limits(), instruments=uneven.instruments)
    assert len(once.attempts) == 1 and once.attempts[0].clean  # batches of 1 and 50 ms: no drift check


def test_production_callers_get_the_machine_clock_sampler_and_pause():
    assert REAL == Instruments(time.perf_counter_ns, Sampler, time.sleep)


def test_on_the_real_clock_each_call_is_timed_whole():
    calls = []
    settings = LoopSettings(3, 0.0, min_iterations=10, min_time_s=0.02, max_time_s=5)
    durations = time_calls(lambda x: (calls.append(x), time.sleep(0.001)), ["a", "b"], settings)
    assert len(durations) >= 10 and len(calls) == len(durations) + 3  # however loaded the machine is
    assert np.all(durations >= MS)  # each timed call slept at least 1 ms: more under load, never less
    out = throughput(lambda x: time.sleep(0.01), None, batch_size=8, seconds=0.05)
    assert out["throughput_batches"] >= 3 and np.all(out["batch_ns"] >= 10 * MS)
    assert 0 < out["throughput_sps"] <= 8 / 0.01  # load only slows it down

"""Interference from what the OS reports: its arithmetic on counts given by hand, and end to end, that a real
CPU-bound competitor on the measuring CPU is seen and gets a timed phase flagged (asserting only what more
load would not change; the re-measuring decisions on scripted figures: test_timing.py)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import replace

import pytest

from bench_matrix.measure import interference, timing
from bench_matrix.measure.interference import (
    CLOCK_TICKS,
    Interference,
    Limits,
    Reading,
    Sampler,
    between,
    cpu_jiffies,
)
from bench_matrix.measure.timing import REAL, LoopSettings, steady_time_calls
from conftest import cli, onnx_matrix_text

CPU = max(os.sched_getaffinity(0))


@contextmanager
def pinned(cpu: int) -> Iterator[None]:
    """This process on one CPU for the block."""
    before = os.sched_getaffinity(0)
    os.sched_setaffinity(0, {cpu})
    try:
        yield
    finally:
        os.sched_setaffinity(0, before)


def start_competitor(cpu: int) -> subprocess.Popen:
    """A CPU-bound process (`while True: pass`) pinned to `cpu`, running once this returns."""
    code = "import sys\nprint('go', flush=True)\nwhile True: pass"
    proc = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, text=True)
    os.sched_setaffinity(proc.pid, {cpu})
    assert proc.stdout.readline() == "go\n"
    return proc


def stop(proc: subprocess.Popen) -> None:
    proc.kill()
    proc.wait()


def spin(seconds: float) -> None:
    end = time.perf_counter() + seconds
    while time.perf_counter() < end:
        pass


def work(_: object) -> None:
    sum(range(20_000))  # about a quarter of a millisecond of pure CPU


def test_proc_stat_is_read_for_every_cpu():
    jiffies = cpu_jiffies()
    assert set(jiffies) >= os.sched_getaffinity(0)
    assert all(busy >= 0 and steal >= 0 for busy, steal in jiffies.values())


def ticks(seconds: float) -> int:
    return round(seconds * CLOCK_TICKS)


def test_the_figures_between_two_readings_are_shares_of_the_window():
    begin = Reading(wall_s=10.0, own_cpu_s=3.0, preemptions=5, cpus=(1,),
                    jiffies={0: (ticks(10), ticks(0.07)), 1: (ticks(20), ticks(0.09))})
    end = Reading(wall_s=12.0, own_cpu_s=4.0, preemptions=505, cpus=(1,),
                  jiffies={0: (ticks(10.6), ticks(0.07)), 1: (ticks(21.8), ticks(0.19)),
                           2: (ticks(0.5), 0)})  # CPU 2 came online meanwhile: left out
    seen = between(begin, end)
    assert (seen.wall_s, seen.cpus, seen.own_cpu_s, seen.preemptions) == (2.0, (1,), 1.0, 500)
    assert seen.other_cpu_s == pytest.approx(0.8)  # CPU 1 was busy 1.8 s, 1 s of it ours
    assert seen.other_share == pytest.approx(0.4) and seen.steal_share == pytest.approx(0.05)
    assert seen.machine_share == pytest.approx((0.6 + 1.8 - 1.0) / (2 * 2.0))  # others' time on both CPUs
    assert seen.cpu_busy == pytest.approx({0: 0.3, 1: 0.9})
    lagging = between(begin, replace(end, own_cpu_s=5.0, jiffies=begin.jiffies))  # our 2 s not yet ticked
    assert lagging.other_cpu_s == 0 and lagging.machine_share == 0  # never less than nothing
    unread = between(replace(begin, jiffies={}), replace(end, jiffies={}))  # no /proc/stat
    assert (unread.other_share, unread.machine_share, unread.steal_share, unread.cpu_busy) == (0, 0, 0, {})


def test_a_competitor_on_the_measuring_cpu_shows_as_other_processes_and_preemptions():
    with pinned(CPU):
        competitor = start_competitor(CPU)
        try:
            sampler = Sampler()
            sampler.start()
            spin(1.0)
            seen = sampler.stop()
        finally:
            stop(competitor)
    assert seen.cpus == (CPU,) and seen.wall_s >= 1.0
    assert seen.own_cpu_s < 0.7 * seen.wall_s  # the scheduler shares the CPU about half and half (or worse)
    assert seen.other_share > Limits().other_share and "of the measuring CPU(s)" in seen.problem(Limits())
    assert seen.preemptions_per_s > 40  # alone: about 10 a second; sharing the CPU: time slices of a few ms


def test_problem_names_each_figure_above_its_limit():
    seen = Interference(wall_s=2.0, cpus=(1,), own_cpu_s=1.0, other_cpu_s=0.9, other_share=0.45,
                        machine_share=0.3, steal_share=0.06, preemptions=500, cpu_busy={0: 0.1, 1: 0.95})
    assert seen.preemptions_per_s == 250
    assert seen.problem(Limits()) == (
        "other processes took 45% of the measuring CPU(s) (limit 5%); other processes took 30% of the "
        "machine's CPU time (limit 25%); CPU steal 6% (limit 3%)")  # preemptions are recorded, not judged
    assert seen.problem(Limits(other_share=0.5, machine_share=0.5, steal_share=0.1)) is None
    stored = seen.as_dict()
    assert stored["cpu_busy"] == {"0": 0.1, "1": 0.95} and stored["preemptions_per_s"] == 250.0


def test_a_window_too_short_for_the_tick_counts_is_recorded_but_never_judged():
    short = Interference(wall_s=interference.JUDGED_FROM_S * 0.9, cpus=(1,), own_cpu_s=0.1, other_cpu_s=0.3,
                         other_share=0.9, machine_share=0.9, steal_share=0.5, preemptions=5, cpu_busy={})
    assert short.problem(Limits()) is None
    assert replace(short, wall_s=interference.JUDGED_FROM_S).problem(Limits()) is not None


def test_a_competitor_that_stays_gets_the_phase_flagged():
    pauses: list[float] = []
    without_pauses = replace(REAL, sleep=pauses.append)  # the machine's clock and sampler; pauses only noted
    settings = LoopSettings(0, 0.0, min_iterations=400, min_time_s=interference.JUDGED_FROM_S,
                            max_time_s=30.0)
    with pinned(CPU):
        competitor = start_competitor(CPU)
        try:
            phase = steady_time_calls(work, [None], settings, Limits(), instruments=without_pauses)
        finally:
            stop(competitor)
    assert len(phase.attempts) == timing.ATTEMPTS and all(a.disturbed for a in phase.attempts)
    assert pauses == [timing.RETRY_PAUSE_S, 2 * timing.RETRY_PAUSE_S]
    assert "other processes took" in phase.disturbed
    record = timing.interference_record({"latency": phase}, Limits())
    assert record["flagged"] is True and record["reason"].startswith("latency: ")


@pytest.mark.slow
def test_a_run_under_a_cpu_bound_competitor_flags_its_cell_and_the_report_marks_it(onnx_project):
    judged = onnx_matrix_text(["tiny"], ["fp32"]).replace(  # long enough to judge
        "min_time_s: 0.02", "min_time_s: 0.5").replace("throughput_time_s: 0.02", "throughput_time_s: 0.5")
    (onnx_project / "m.yaml").write_text(judged)
    env = {"BENCH_MATRIX_LOCK_DIR": str(onnx_project / "lock")}
    competitors = [start_competitor(cpu) for cpu in sorted(os.sched_getaffinity(0))]  # whichever CPU it pins
    try:
        run = cli(onnx_project, "run", "m.yaml", env=env)
    finally:
        for proc in competitors:
            stop(proc)
    assert run.returncode == 0, run.stdout + run.stderr
    (record,) = json.loads(cli(onnx_project, "report", "--format", "json").stdout)
    seen = record["metrics"]["interference"]
    latency = seen["phases"]["latency"]
    assert len(latency["attempts"]) == timing.ATTEMPTS  # re-measured, disturbed every time
    assert seen["flagged"] is True and "other processes took" in seen["reason"]
    assert all(a["other_share"] > Limits().other_share for a in latency["attempts"])
    assert record["metrics"]["latency_attempts"] == timing.ATTEMPTS
    cli(onnx_project, "report", "--format", "md", "--out", str(onnx_project / "pages"))
    page = (onnx_project / "pages" / "tiny.md").read_text()
    assert "> **Disturbed (~):** onnxruntime none fp32: latency: other processes took" in page

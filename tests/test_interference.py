"""Interference from what the OS reports: its arithmetic on counts given by hand, and end to end, that a real
CPU-bound competitor on the measuring CPU is seen and gets a timed phase flagged (asserting only what more
load would not change; the rounds' decisions on scripted windows: test_rounds.py)."""

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

from bench_matrix.measure import interference
from bench_matrix.measure.interference import (
    CLOCK_TICKS,
    Interference,
    Limits,
    Reading,
    Sampler,
    between,
    cpu_jiffies,
)
from bench_matrix.measure.timing import latency_window
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
    # alone: about 10 preemptions a second of its own CPU time; sharing the CPU, time slices of a few ms: over
    # 40 a CPU second however many other processes share it too (per wall second it falls with their number)
    assert seen.preemptions / seen.own_cpu_s > 40, seen


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


def test_a_window_too_short_for_the_tick_counts_is_judged_with_their_error_taken_off():
    error = interference.COUNTING_ERROR_S
    wall = interference.JUDGED_FROM_S / 2  # 20 ticks: two of them are 10 % of the window
    gross = Interference(wall_s=wall, cpus=(1,), own_cpu_s=0.1, other_cpu_s=0.3, other_share=0.9,
                         machine_share=0.9, steal_share=0.5, preemptions=5, cpu_busy={})
    assert "took 90% of the measuring CPU" in gross.problem(Limits())  # gross work counts at any length
    just = Limits().other_share + error / wall  # the limit plus the counting error: not yet disturbed
    slight = replace(gross, other_share=just - 0.001, machine_share=0.0, steal_share=0.0)
    assert slight.problem(Limits()) is None
    assert replace(slight, other_share=just + 0.001).problem(Limits()) is not None
    long = replace(slight, wall_s=interference.JUDGED_FROM_S)  # long enough: judged as counted
    assert long.problem(Limits()) is not None


def test_a_competitor_on_the_measuring_cpu_disturbs_a_window():
    seconds = interference.JUDGED_FROM_S
    with pinned(CPU):
        competitor = start_competitor(CPU)
        try:
            sampler = Sampler()
            durations = latency_window(work, [None], seconds, sampler)
            seen = sampler.stop()
        finally:
            stop(competitor)
    assert len(durations) >= 1 and seen.wall_s >= seconds
    assert "other processes took" in (seen.problem(Limits()) or "")


@pytest.mark.slow
def test_a_run_under_a_cpu_bound_competitor_flags_its_cell_and_the_report_marks_it(onnx_project):
    judged = onnx_matrix_text(["tiny"], ["fp32"]).replace(  # windows long enough to judge as counted
        "window_s: 0.01", "window_s: 0.4").replace("timing_budget_s: 0.05", "timing_budget_s: 2")
    (onnx_project / "m.yaml").write_text(judged)
    env = {"BENCH_MATRIX_LOCK_DIR": str(onnx_project / "lock")}
    competitors = [start_competitor(cpu) for cpu in sorted(os.sched_getaffinity(0))]  # whichever CPU it pins
    try:
        run = cli(onnx_project, "run", "m.yaml", env=env)
    finally:
        for proc in competitors:
            stop(proc)
    assert run.returncode == 0, run.stdout + run.stderr
    (record,) = json.loads(cli(onnx_project, "report", "--format", "json").stdout)["records"]
    seen = record["metrics"]["interference"]
    latency = seen["phases"]["latency"]
    assert latency["dropped"] > latency["windows"] * 0.25  # disturbed in (nearly) every window
    assert seen["flagged"] is True and "other processes took" in seen["reason"]
    cli(onnx_project, "report", "--format", "md", "--out", str(onnx_project / "pages"))
    page = (onnx_project / "pages" / "tiny.md").read_text()
    assert "> **Disturbed (~):** onnxruntime none fp32: latency: " in page and "windows disturbed" in page

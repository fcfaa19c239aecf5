"""The statistics over interleaved rounds (bench_matrix.measure.rounds): coverage on simulated drifting runs,
paired against unpaired speed-ups, and the arithmetic itself. Nothing here reads the real clock."""

from __future__ import annotations

import math
import random

import numpy as np
import pytest

from bench_matrix.measure.rounds import (Interval, log_interval, medians_by_round, p50_interval,
                                         rate_interval, speedup, t95)
from bench_matrix.measure.schedule import LATENCY, Timed, paired
from bench_matrix.measure.stats import median_interval
from rounds_sim import NEVER_NARROW, FakeSession, Machine, rounds_on


# --- statistics under drift ---------------------------------------------------------------------------------

BASE_MS = 10.0


def drifting_runs(rng: np.random.Generator, runs: int, rounds: int, calls: int, drift_sigma: float,
                  noise_sigma: float, round_corr: float) -> np.ndarray:
    """Durations (runs, rounds, calls): log speed a stationary AR(1) over rounds (sd `drift_sigma`,
    correlation `round_corr` from one round to the next: it moves on the scale of a round, held through each
    window), times iid lognormal noise. The log of every sample is symmetric about log BASE_MS, so BASE_MS is
    the median of the process over any long run."""
    level = np.empty((runs, rounds))
    level[:, 0] = rng.normal(0.0, drift_sigma, runs)
    for r in range(1, rounds):
        fresh = rng.normal(0.0, drift_sigma * math.sqrt(1 - round_corr**2), runs)
        level[:, r] = round_corr * level[:, r - 1] + fresh
    return BASE_MS * np.exp(level[:, :, None] + rng.normal(0.0, noise_sigma, (runs, rounds, calls)))


def coverages(samples: np.ndarray) -> tuple[float, float]:
    """How often BASE_MS lies in the round-based p50 interval, and in the iid interval of pooled samples."""
    by_rounds = pooled = 0
    for run in samples:
        interval = p50_interval(dict(enumerate(run)))
        by_rounds += interval.low <= BASE_MS <= interval.high
        low, high = median_interval(run.ravel())
        pooled += low <= BASE_MS <= high
    return by_rounds / len(samples), pooled / len(samples)


def test_the_process_median_is_the_base_time():
    long_run = drifting_runs(np.random.default_rng(0), 1, 20_000, 50, 0.05, 0.03, 0.1)
    assert np.median(long_run) == pytest.approx(BASE_MS, rel=5e-4)


def test_round_intervals_cover_the_median_under_drift_where_pooled_iid_intervals_do_not():
    samples = drifting_runs(np.random.default_rng(6), 300, 20, 50, drift_sigma=0.05, noise_sigma=0.03,
                            round_corr=0.1)
    by_rounds, pooled = coverages(samples)
    assert by_rounds >= 0.85  # ~0.93 here (0.95 stated)
    assert pooled < 0.5  # ~0.27: 1000 samples look precise, but they come from 20 drifting levels
    widths = [p50_interval(dict(enumerate(run))).half_width for run in samples]
    assert 0.022 < float(np.median(widths)) < 0.05  # the drift widens it: 1.41 * 2.09 * 0.05 / sqrt(20) = 0.033


def test_a_reruns_p50_falls_in_the_stated_interval():
    """Two runs of the same drifting process: run 2's pooled p50 lies in run 1's interval about 95 % of the
    time (an interval of the first run's level alone would cover it about 83 %)."""
    first, second = np.split(drifting_runs(np.random.default_rng(8), 600, 12, 50, drift_sigma=0.03,
                                           noise_sigma=0.03, round_corr=0.1), 2)
    inside = [(i := p50_interval(dict(enumerate(a)))).low <= float(np.median(b)) <= i.high
              for a, b in zip(first, second)]
    assert 0.9 <= sum(inside) / len(inside) <= 0.99


def test_without_drift_both_intervals_cover_the_median():
    samples = drifting_runs(np.random.default_rng(7), 300, 20, 50, drift_sigma=0.0, noise_sigma=0.03,
                            round_corr=0.0)
    by_rounds, pooled = coverages(samples)
    assert by_rounds >= 0.88 and pooled >= 0.88
    assert float(np.median([p50_interval(dict(enumerate(run))).half_width for run in samples])) < 0.004


def test_paired_speedup_cancels_the_drift_both_cells_share():
    """Baseline and a cell twice as fast on one machine whose speed swings ±10 % slowly (a sine of 20 s
    period over 12 s of rounds, random phase): the paired interval is far narrower than the unpaired one
    and covers 2."""
    covered, paired_widths, unpaired_widths = 0, [], []
    for seed in range(40):
        phase = random.Random(seed).uniform(0, 2 * math.pi)
        swing = lambda t, phase=phase: math.exp(0.1 * math.sin(2 * math.pi * t / 20 + phase))  # noqa: E731
        machine = Machine(seed, drift=swing)
        sessions = {"base": FakeSession(machine, "base", base_ms=10.0, noise=0.03),
                    "fast": FakeSession(machine, "fast", base_ms=5.0, noise=0.03)}
        timed = {name: Timed() for name in sessions}
        rounds_on(machine, seed=seed, max_rounds=40, target=NEVER_NARROW).run(sessions, timed, "base", 1e9)
        ratio = paired(timed["base"], timed["fast"])
        assert ratio.rounds == 40
        covered += ratio.low <= 2.0 <= ratio.high
        paired_widths.append(ratio.half_width)
        halves = [p50_interval(timed[name].series(LATENCY)).half_width for name in sessions]
        unpaired_widths.append(math.hypot(*halves))
    assert covered / 40 >= 0.85
    assert float(np.median(paired_widths)) < float(np.median(unpaired_widths)) / 3
    assert max(paired_widths) < 0.01 < float(np.median(unpaired_widths))


# --- the statistics themselves ------------------------------------------------------------------------------


@pytest.mark.parametrize("df, quantile, rel", [(1, 12.706, 1e-4), (10, 2.228, 1e-4), (30, 2.042, 1e-4),
                                               (31, 2.0395, 3e-3), (60, 2.000, 3e-3), (120, 1.980, 3e-3),
                                               (10_000, 1.960, 3e-3)])
def test_t95_matches_student_quantiles(df, quantile, rel):
    assert t95(df) == pytest.approx(quantile, rel=rel)


def test_log_interval_is_a_t_interval_on_the_logs():
    interval = log_interval(2.0, [1.0, 2.0, 4.0])
    half = 4.303 * math.log(2) / math.sqrt(3)  # sd of (0, ln 2, 2 ln 2) is ln 2; df 2
    assert interval.low == pytest.approx(2.0 * math.exp(-half))
    assert interval.high == pytest.approx(2.0 * math.exp(half))
    assert interval.value == 2.0 and interval.rounds == 3
    assert interval.half_width == pytest.approx(math.exp(half) - 1)  # the upper side is the larger one


@pytest.mark.filterwarnings("ignore:divide by zero:RuntimeWarning", "ignore:invalid value:RuntimeWarning")
@pytest.mark.parametrize("value, per_round", [(5.0, []), (5.0, [5.0]), (0.0, [1.0, 2.0]), (-1.0, [1.0, 2.0]),
                                              (5.0, [4.0, 0.0]), (5.0, [4.0, -6.0])])
def test_log_interval_needs_two_positive_rounds(value, per_round):
    assert log_interval(value, per_round) is None


def test_interval_half_width_is_the_larger_side_relative_to_the_value():
    assert Interval(10.0, 9.0, 10.5, 4).half_width == pytest.approx(0.1)
    assert Interval(10.0, 9.8, 10.3, 4).half_width == pytest.approx(0.03)
    assert Interval(10.0, 9.0, 10.5, 4).as_dict() == {"value": 10.0, "ci": [9.0, 10.5], "ci_half": 0.1,
                                                       "rounds": 4}


def test_p50_interval_pools_the_windows_and_spreads_the_round_medians():
    series = {0: np.array([1.0, 2.0, 3.0]), 1: np.array([4.0, 5.0, 60.0]), 2: np.array([]),
              3: np.array([7.0])}
    assert medians_by_round(series) == {0: 2.0, 1: 5.0, 3: 7.0}
    interval = p50_interval(series)
    assert interval.value == 4.0 and interval.rounds == 3  # the pooled median (mean 11.7); 3 rounds counted
    assert interval == log_interval(4.0, [2.0, 5.0, 7.0], spread=math.sqrt(2))  # where a rerun's would fall
    level = log_interval(4.0, [2.0, 5.0, 7.0])  # the interval of this run's level alone
    assert math.log(interval.high / 4.0) == pytest.approx(math.sqrt(2) * math.log(level.high / 4.0))
    assert p50_interval({}) is None and p50_interval({0: np.array([1.0, 2.0])}) is None


def test_speedup_pairs_the_rounds_both_cells_have():
    baseline = {0: 10.0, 1: 20.0, 2: 12.0, 3: 11.0}
    cell = {0: 5.0, 1: 10.0, 2: 6.0, 4: 1.0}  # drift doubled both in round 1: every paired ratio is 2
    ratio = speedup(baseline, cell)
    assert (ratio.value, ratio.low, ratio.high, ratio.rounds) == (pytest.approx(2.0), pytest.approx(2.0),
                                                                  pytest.approx(2.0), 3)
    uneven = speedup({0: 10.0, 1: 10.0}, {0: 4.0, 1: 5.0})
    assert uneven.value == pytest.approx(math.sqrt(2.5 * 2.0)) and uneven.rounds == 2  # geometric mean
    assert speedup({0: 10.0, 1: 10.0}, {0: 5.0, 2: 5.0}) is None  # one round in common
    assert speedup({0: 10.0, 1: 10.0, 2: 10.0}, {0: 5.0, 1: 0.0, 2: 4.0}).rounds == 2  # a zero time skipped


def test_rate_interval_is_samples_per_second_with_the_spread_of_round_rates():
    interval = rate_interval({0: 90.0, 1: 110.0, 2: 100.0}, samples=3000, seconds=30.0)
    assert interval.value == 100.0 and interval.rounds == 3
    assert interval == log_interval(100.0, [90.0, 110.0, 100.0], spread=math.sqrt(2))  # where a rerun's falls
    assert rate_interval({0: 90.0, 1: 110.0}, samples=3000, seconds=0.0) is None

"""The arithmetic of the rounds' statistics (bench_matrix.measure.rounds) on hand-made values: t quantiles,
intervals of levels, process spreads, p50, speed-up and rate intervals."""

from __future__ import annotations

import math

import numpy as np
import pytest

from bench_matrix.measure.rounds import (Interval, Spread, level_interval, log_levels, medians, moderated,
                                         p50_interval, pooled, process_spread, rate_interval, speedup, t95)
from rounds_sim import one


@pytest.mark.parametrize("df, quantile, rel", [(1, 12.706, 1e-4), (10, 2.228, 1e-4), (30, 2.042, 1e-4),
                                               (31, 2.0395, 3e-3), (60, 2.000, 3e-3), (120, 1.980, 3e-3),
                                               (10_000, 1.960, 3e-3)])
def test_t95_matches_student_quantiles(df, quantile, rel):
    assert t95(df) == pytest.approx(quantile, rel=rel)


def test_two_rounds_whose_medians_agree_exactly_are_known_to_their_windows_own_median_error_not_to_zero():
    """Seen in CI: two windows of a 6 µs model with the same median to the nanosecond gave a 0-wide
    interval and stopped the rounds; the rounds' spread is at least a window median's own error."""
    rng = np.random.default_rng(0)
    calls = 1500
    first = np.round(5.969e-3 + rng.normal(0.0, 2e-5, calls), 6)  # ms, to the nanosecond
    second = first[rng.permutation(calls)]  # other calls, the same median
    assert np.median(first) == np.median(second)
    interval = p50_interval(one([first, second]))
    error = math.sqrt(math.pi / 2) * 2e-5 / math.sqrt(calls) / 5.969e-3  # a median's standard error, relative
    # RERUN (√2) × t(1 dof) × √(error² ÷ 2 rounds)
    assert interval.half_width == pytest.approx(t95(1) * error, rel=0.15)


def test_a_single_process_interval_is_a_t_interval_on_the_logs():
    interval = level_interval(2.0, log_levels(one([1.0, 2.0, 4.0])), None)
    half = 4.303 * math.log(2) / math.sqrt(3)  # sd of (0, ln 2, 2 ln 2) is ln 2; df 2
    assert interval.low == pytest.approx(2.0 * math.exp(-half))
    assert interval.high == pytest.approx(2.0 * math.exp(half))
    assert interval.value == 2.0 and interval.rounds == 3
    assert interval.half_width == pytest.approx(math.exp(half) - 1)  # the upper side is the larger one


@pytest.mark.parametrize("value, per_round", [(5.0, []), (5.0, [5.0]), (0.0, [1.0, 2.0]), (-1.0, [1.0, 2.0]),
                                              (5.0, [4.0, 0.0]), (5.0, [4.0, -6.0])])
def test_an_interval_needs_two_positive_rounds(value, per_round):
    assert level_interval(value, log_levels(one(per_round)), None) is None


def test_process_spread_is_how_far_each_process_sits_from_the_rounds_means():
    # two processes, 3 rounds: the round drift (x1, x2, x4) is shared; process 1 is always 10 % slower
    drift = enumerate([1.0, 2.0, 4.0])
    levels = log_levels({(r, j): d * (1.1 if j else 1.0) for r, d in drift for j in (0, 1)})
    found = process_spread(levels)
    assert found.dof == 1 and found.variance == pytest.approx(2 * (math.log(1.1) / 2) ** 2)
    assert process_spread(log_levels(one([1.0, 2.0]))) is None  # one process
    assert process_spread(log_levels({(0, 0): 1.0, (0, 1): 1.1})) is None  # one round
    # the process part enters the interval: t(Satterthwaite df) * sqrt(rounds' part + spread / processes)
    interval = level_interval(2.0, levels, None)
    assert interval.rounds == 3
    rounds_part = float(np.var([math.log(d) + math.log(1.1) / 2 for d in (1, 2, 4)], ddof=1)) / 3
    process_part = found.variance / 2
    df = (rounds_part + process_part) ** 2 / (rounds_part ** 2 / 2 + process_part ** 2 / 1)
    assert math.log(interval.high / 2.0) == pytest.approx(t95(df) * math.sqrt(rounds_part + process_part))


def test_pooled_and_moderated_spreads():
    a, b = Spread(0.0004, 1), Spread(0.0001, 3)
    assert pooled([a, None, b]) == Spread(pytest.approx(0.000175), 4)
    assert pooled([None]) is None
    model = Spread(0.0001, 20)  # a cell's own 1-dof spread drawn towards the model's, counted as 4 dof
    assert moderated(a, model) == Spread(pytest.approx((4 * 0.0001 + 0.0004) / 5), 5)
    assert moderated(a, Spread(0.0001, 2)).dof == 3  # a model of few processes counts as what it has
    assert moderated(None, model) is model and moderated(a, None) is a
    assert Spread(0.0004, 1).relative == pytest.approx(0.02)


def test_interval_half_width_is_the_larger_side_relative_to_the_value():
    assert Interval(10.0, 9.0, 10.5, 4).half_width == pytest.approx(0.1)
    assert Interval(10.0, 9.8, 10.3, 4).half_width == pytest.approx(0.03)
    assert Interval(10.0, 9.0, 10.5, 4).as_dict() == {"value": 10.0, "ci": [9.0, 10.5], "ci_half": 0.1,
                                                       "rounds": 4}


def test_p50_interval_pools_the_windows_and_spreads_the_round_medians():
    series = one([np.array([1.0, 2.0, 3.0]), np.array([4.0, 5.0, 60.0]), np.array([]), np.array([7.0])])
    assert medians(series) == {(0, 0): 2.0, (1, 0): 5.0, (3, 0): 7.0}
    interval = p50_interval(series)
    assert interval.value == 4.0 and interval.rounds == 3  # the pooled median (mean 11.7); 3 rounds counted
    levels = log_levels({(0, 0): 2.0, (1, 0): 5.0, (3, 0): 7.0})
    assert interval == level_interval(4.0, levels, None, spread=math.sqrt(2))  # where a rerun's would fall
    level = level_interval(4.0, levels, None)  # the interval of this run's level alone
    assert math.log(interval.high / 4.0) == pytest.approx(math.sqrt(2) * math.log(level.high / 4.0))
    assert p50_interval({}) is None and p50_interval(one([np.array([1.0, 2.0])])) is None


def test_speedup_pairs_the_rounds_both_cells_have():
    baseline = one([10.0, 20.0, 12.0, 11.0])
    cell = {(0, 0): 5.0, (1, 0): 10.0, (2, 0): 6.0, (4, 0): 1.0}  # drift doubled both in round 1: ratios 2
    ratio = speedup(baseline, cell)
    assert (ratio.value, ratio.low, ratio.high, ratio.rounds) == (pytest.approx(2.0), pytest.approx(2.0),
                                                                  pytest.approx(2.0), 3)
    uneven = speedup(one([10.0, 10.0]), one([4.0, 5.0]))
    assert uneven.value == pytest.approx(math.sqrt(2.5 * 2.0)) and uneven.rounds == 2  # geometric mean
    assert speedup(one([10.0, 10.0]), {(0, 0): 5.0, (2, 0): 5.0}) is None  # one round in common
    assert speedup(one([10.0, 10.0, 10.0]), one([5.0, 0.0, 4.0])).rounds == 2  # a zero time skipped


def test_a_speedup_pairs_each_rounds_mean_over_the_processes_and_adds_their_spreads():
    # each cell in 2 processes 10 % apart; every round's mean ratio is the same: only the processes widen it
    base = {(r, j): 10.0 * (1.1 if j else 1.0) for r in range(4) for j in (0, 1)}
    cell = {(r, j): 5.0 * (1.1 if j else 1.0) for r in range(4) for j in (0, 1)}
    ratio = speedup(base, cell)
    assert ratio.value == pytest.approx(2.0) and ratio.rounds == 4
    variance = process_spread(log_levels(base)).variance
    assert math.log(ratio.high / 2.0) == pytest.approx(t95(2) * math.sqrt(2 * variance / 2))


def test_rate_interval_is_samples_per_second_with_the_spread_of_round_rates():
    interval = rate_interval(one([90.0, 110.0, 100.0]), samples=3000, seconds=30.0)
    assert interval.value == 100.0 and interval.rounds == 3
    rerun = level_interval(100.0, log_levels(one([90.0, 110.0, 100.0])), None, spread=math.sqrt(2))
    assert interval == rerun  # where a rerun's falls
    assert rate_interval(one([90.0, 110.0]), samples=3000, seconds=0.0) is None

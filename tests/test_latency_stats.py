"""The median's confidence interval (order statistics) and the stored form of raw latencies."""

from __future__ import annotations

import math

import numpy as np
import pytest

from bench_matrix.measure.stats import median_interval, median_ranks, pack_samples, unpack_samples

DRAWS = 4000
DISTRIBUTIONS = {  # name: (draw n values, true median)
    "normal": (lambda rng, n: rng.normal(1.0, 0.1, n), 1.0),
    "lognormal": (lambda rng, n: rng.lognormal(0.0, 0.5, n), 1.0),
    "exponential": (lambda rng, n: rng.exponential(1.0, n), math.log(2)),
}


def exact_coverage(n: int) -> float:
    """1 - 2 P(X <= k-1) for X ~ Binomial(n, 1/2), k the interval's 1-based lower rank."""
    lo, _ = median_ranks(n)
    return 1 - 2 * sum(math.comb(n, j) for j in range(lo + 1)) / 2**n


@pytest.mark.parametrize("n, ranks", [(5, None), (6, (0, 5)), (10, (1, 8)), (20, (5, 14)), (100, (39, 60))])
def test_median_ranks_match_the_binomial_table(n, ranks):
    assert median_ranks(n) == ranks  # 1-based tables: n=10 -> x(2), x(9); n=100 -> x(40), x(61)


def test_median_ranks_of_large_samples_follow_the_normal_approximation():
    n = 100_000
    lo, hi = median_ranks(n)
    half = 1.959964 * math.sqrt(n) / 2
    assert abs(lo - (n / 2 - half)) <= 2 and abs(hi - (n / 2 + half)) <= 2 and lo + hi == n - 1


@pytest.mark.parametrize("name", sorted(DISTRIBUTIONS))
@pytest.mark.parametrize("n", [20, 101, 1000])
def test_intervals_cover_the_true_median_at_the_stated_rate(name, n):
    draw, median = DISTRIBUTIONS[name]
    rng = np.random.default_rng([n, len(name)])  # seeded: the same draws every run
    covered = 0
    for _ in range(DRAWS):
        lo, hi = median_interval(draw(rng, n))
        covered += lo <= median <= hi
    rate, expected = covered / DRAWS, exact_coverage(n)
    assert 0.95 <= expected < 0.97  # the largest rank keeping at least 95 %: never much more
    tolerance = 4 * math.sqrt(expected * (1 - expected) / DRAWS)  # four standard errors of the rate
    assert abs(rate - expected) <= tolerance, (rate, expected)


def test_no_interval_below_six_samples():
    assert median_interval(np.array([1.0, 2.0, 3.0, 4.0, 5.0])) is None
    assert median_interval(np.arange(6.0)) == (0.0, 5.0)


def test_packed_samples_round_trip_as_float32_milliseconds():
    durations_ns = np.random.default_rng(0).integers(50_000, 5_000_000, 10_000)
    blob = pack_samples(durations_ns)
    ms = unpack_samples(blob)
    assert ms.dtype == np.float32 and len(ms) == 10_000
    assert np.allclose(ms, durations_ns / 1e6, rtol=1e-7)
    assert len(blob) < 4 * 10_000  # compressed below the raw float32 bytes

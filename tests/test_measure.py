"""Statistics, sizes and the timing loop, checked against values computed by hand (accuracy: test_metrics.py)."""

from __future__ import annotations

import gzip
import time

import numpy as np
import pytest

from bench_matrix.measure import interference, timing
from bench_matrix.measure.interference import Limits
from bench_matrix.measure.size import artifact_size
from bench_matrix.measure.stats import latency_summary
from bench_matrix.measure.timing import LoopSettings, drift, steady_time_calls, throughput, time_calls

INF = float("inf")
NO_LIMITS = Limits(other_share=INF, machine_share=INF, steal_share=INF)  # only drift makes a window unclean


def test_latency_summary_percentiles_and_units():
    durations_ns = np.arange(1, 101) * 1_000_000  # 1..100 ms
    s = latency_summary(durations_ns)
    assert s["n"] == 100 and s["min"] == 1.0
    assert s["mean"] == pytest.approx(50.5)
    assert s["p50"] == pytest.approx(50.5)  # linear interpolation between the 50th and 51st values
    assert s["p90"] == pytest.approx(90.1)
    assert s["p99"] == pytest.approx(99.01)
    assert s["std"] == pytest.approx(np.std(np.arange(1, 101), ddof=1))
    assert s["p50_ci"] == [40.0, 61.0]  # the 40th and 61st of 100 ordered values (binomial table)
    assert s["p50_ci_rel"] == pytest.approx(21 / 50.5)
    assert latency_summary(np.arange(1, 6) * 1_000_000)["p50_ci"] is None  # n = 5: no 95 % interval exists


def test_latency_summary_rejects_empty():
    with pytest.raises(ValueError):
        latency_summary(np.array([], dtype=np.int64))


def test_artifact_size_sums_every_file_and_compresses(tmp_path):
    (tmp_path / "sub").mkdir()
    (tmp_path / "a.bin").write_bytes(b"\0" * 100_000)
    (tmp_path / "sub" / "b.bin").write_bytes(np.random.default_rng(0).bytes(50_000))
    size = artifact_size(tmp_path)
    assert size["size_bytes"] == 150_000 and size["files"] == 2
    zeros = len(gzip.compress(b"\0" * 100_000, compresslevel=9, mtime=0))
    assert zeros < 1000 and size["size_gzip_bytes"] > 50_000  # sparse data shrinks, random data does not


def test_artifact_size_is_kept_while_the_files_are_unchanged(tmp_path):
    model, cache = tmp_path / "model", tmp_path / "size.json"
    model.mkdir()
    (model / "a.bin").write_bytes(b"\0" * 10_000)
    first = artifact_size(model, cache)
    assert cache.is_file() and artifact_size(model, cache) == first
    kept = cache.read_text()
    cache.write_text(kept.replace(f'"size_gzip_bytes": {first["size_gzip_bytes"]}', '"size_gzip_bytes": 7'))
    assert artifact_size(model, cache)["size_gzip_bytes"] == 7  # read back, not recomputed
    (model / "b.bin").write_bytes(b"\1" * 10)  # a new file (a TensorRT engine written at load): measured again
    again = artifact_size(model, cache)
    assert again["files"] == 2 and again["size_bytes"] == 10_010 and again["size_gzip_bytes"] > 7


def test_time_calls_meets_both_minimums():
    calls = []
    settings = LoopSettings(warmup_iterations=3, warmup_s=0.0, min_iterations=10, min_time_s=0.05, max_time_s=5)
    durations = time_calls(lambda x: (calls.append(x), time.sleep(0.001)), ["a", "b"], settings)
    assert len(durations) >= 10
    assert durations.sum() >= 0.05e9 * 0.9  # the measured time covers the minimum duration
    assert len(calls) == len(durations) + 3  # warm-up calls are not timed
    assert np.all(durations >= 1_000_000)  # each timed call slept at least 1 ms
    assert set(calls) == {"a", "b"}  # inputs are cycled


def test_time_calls_stops_at_max_time():
    settings = LoopSettings(0, 0.0, min_iterations=10_000, min_time_s=0.0, max_time_s=0.05)
    durations = time_calls(lambda x: time.sleep(0.005), [None], settings)
    assert 3 <= len(durations) < 100


def test_throughput_counts_samples_per_second():
    out = throughput(lambda x: time.sleep(0.01), None, batch_size=8, seconds=0.1)
    assert out["throughput_batches"] >= 3
    assert 8 / 0.02 < out["throughput_sps"] <= 8 / 0.01 * 1.05


def test_drift_is_zero_for_steady_and_large_for_a_step():
    steady = np.full(100, 1_000_000)
    assert drift(steady) == 0.0
    step = np.concatenate([np.full(50, 1_000_000), np.full(50, 1_500_000)])  # interference half-way
    assert drift(step) == pytest.approx(0.5 / 1.25)


def test_steady_time_calls_repeats_a_drifting_measurement_and_keeps_the_clean_one(monkeypatch):
    monkeypatch.setattr(timing, "RETRY_PAUSE_S", 0.0)
    calls = {"n": 0}

    def call(_):
        calls["n"] += 1
        time.sleep(0.004 if 10 <= calls["n"] <= 20 else 0.001)  # a slow spell in the middle of attempt 1

    settings = LoopSettings(0, 0.0, min_iterations=40, min_time_s=0.0, max_time_s=5)
    phase = steady_time_calls(call, [None], settings, NO_LIMITS, attempts=3)
    assert len(phase.attempts) == 2 and phase.kept == 1 and phase.attempts[1].clean
    assert "chunk medians drifted" in phase.attempts[0].unsteady and phase.attempts[0].disturbed is None
    assert drift(phase.result) <= timing.DRIFT_LIMIT and np.median(phase.result) < 2_500_000


def test_a_phase_disturbed_in_every_attempt_keeps_the_lowest_median_and_says_why(monkeypatch):
    monkeypatch.setattr(timing, "RETRY_PAUSE_S", 0.0)
    monkeypatch.setattr(interference, "JUDGED_FROM_S", 0.0)  # windows of 60 ms: judge them all the same
    sleeps = iter([0.003] * 20 + [0.001] * 20 + [0.002] * 20)  # three attempts, the second the fastest

    def call(_):
        time.sleep(next(sleeps))

    settings = LoopSettings(0, 0.0, min_iterations=20, min_time_s=0.0, max_time_s=5)
    strict = Limits(other_share=-1.0, machine_share=INF, steal_share=INF)  # every window counts as disturbed
    phase = steady_time_calls(call, [None], settings, strict, attempts=3)
    assert len(phase.attempts) == 3 and phase.kept == 1
    assert "of the measuring CPU(s) (limit -100%)" in phase.disturbed
    record = timing.interference_record({"latency": phase}, strict)
    assert record["flagged"] is True and record["reason"].startswith("latency: other processes took")
    assert record["phases"]["latency"]["kept"] == 1 and len(record["phases"]["latency"]["attempts"]) == 3
    assert set(record["phases"]["latency"]["attempts"][0]) >= {
        "p50_ms", "p99_ms", "n", "other_share", "machine_share", "steal_share", "preemptions_per_s", "wall_s",
        "disturbed", "unsteady"}


def test_drift_alone_re_measures_but_never_flags(monkeypatch):
    monkeypatch.setattr(timing, "RETRY_PAUSE_S", 0.0)
    sleeps = iter(([0.001] * 10 + [0.003] * 10) * 3)  # every attempt slows down half-way

    def call(_):
        time.sleep(next(sleeps))

    settings = LoopSettings(0, 0.0, min_iterations=20, min_time_s=0.0, max_time_s=5)
    phase = steady_time_calls(call, [None], settings, NO_LIMITS, attempts=3)
    assert len(phase.attempts) == 3 and all(a.unsteady and a.disturbed is None for a in phase.attempts)
    assert phase.disturbed is None
    assert timing.interference_record({"latency": phase}, NO_LIMITS)["flagged"] is False


def test_time_calls_goes_on_until_the_median_interval_is_narrow():
    durations = iter(np.tile([0.0005, 0.003], 10_000))  # two modes: the median's interval spans both

    def call(_):
        time.sleep(next(durations))

    wide = LoopSettings(0, 0.0, min_iterations=20, min_time_s=0.0, max_time_s=0.3, ci_rel_width=0.05)
    timed = time_calls(call, [None], wide)
    assert timed.sum() >= 0.3e9 * 0.95 and len(timed) > 20  # never narrow: ran up to max_time_s
    loose = LoopSettings(0, 0.0, min_iterations=20, min_time_s=0.0, max_time_s=0.3, ci_rel_width=1.0)
    assert len(time_calls(lambda _: time.sleep(0.001), [None], loose)) == 20  # narrow at once: the minimum

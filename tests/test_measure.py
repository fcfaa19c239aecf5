"""Statistics, sizes and the timing loop, checked against values computed by hand (accuracy: test_metrics.py)."""

from __future__ import annotations

import gzip
import time

import numpy as np
import pytest

from bench_matrix.measure.size import artifact_size
from bench_matrix.measure.stats import latency_summary
from bench_matrix.measure.timing import LoopSettings, drift, steady_time_calls, throughput, time_calls


def test_latency_summary_percentiles_and_units():
    durations_ns = np.arange(1, 101) * 1_000_000  # 1..100 ms
    s = latency_summary(durations_ns)
    assert s["n"] == 100 and s["min"] == 1.0
    assert s["mean"] == pytest.approx(50.5)
    assert s["p50"] == pytest.approx(50.5)  # linear interpolation between the 50th and 51st values
    assert s["p90"] == pytest.approx(90.1)
    assert s["p99"] == pytest.approx(99.01)
    assert s["std"] == pytest.approx(np.std(np.arange(1, 101), ddof=1))


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


def test_steady_time_calls_repeats_an_unsteady_measurement_and_keeps_the_steadiest():
    calls = {"n": 0}

    def call(_):
        calls["n"] += 1
        time.sleep(0.004 if 10 <= calls["n"] <= 20 else 0.001)  # interference in the middle of attempt 1

    settings = LoopSettings(0, 0.0, min_iterations=20, min_time_s=0.0, max_time_s=5)
    durations, info = steady_time_calls(call, [None], settings, tolerance=0.2, attempts=3)
    assert info["latency_attempts"] == 2 and info["latency_stability"] <= 0.2
    assert np.median(durations) < 2_500_000  # the kept attempt is the steady, fast one

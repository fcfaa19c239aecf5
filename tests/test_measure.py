"""Statistics and sizes, checked against values computed by hand (accuracy: test_metrics.py; the timing loops:
test_timing.py)."""

from __future__ import annotations

import gzip

import numpy as np
import pytest

from bench_matrix.measure.size import artifact_size
from bench_matrix.measure.stats import latency_summary


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
    model, cache, partial = tmp_path / "model", tmp_path / "size.json", tmp_path / "partial-size.json"
    model.mkdir()
    (model / "a.bin").write_bytes(b"\0" * 10_000)
    first = artifact_size(model, cache, partial)
    assert cache.is_file() and not partial.exists() and artifact_size(model, cache) == first
    kept = cache.read_text()
    cache.write_text(kept.replace(f'"size_gzip_bytes": {first["size_gzip_bytes"]}', '"size_gzip_bytes": 7'))
    assert artifact_size(model, cache)["size_gzip_bytes"] == 7  # read back, not recomputed
    (model / "b.bin").write_bytes(b"\1" * 10)  # a new file (a TensorRT engine written at load): measured again
    again = artifact_size(model, cache, partial)
    assert again["files"] == 2 and again["size_bytes"] == 10_010 and again["size_gzip_bytes"] > 7

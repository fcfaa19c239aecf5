"""Run history end to end: runs are kept, `compare` gates on a planted regression, stores of two hosts merge,
and a store of the previous release is reported and extended."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest

from bench_matrix.measure.interference import COUNTING_ERROR_S
from conftest import FAST_SETTINGS, cli, install_slow_plugin, matrix_text, onnx_matrix_text

FORMAT_1 = Path(__file__).parent / "data" / "store-format-1.sqlite"
pytestmark = pytest.mark.slow


def _ok(out) -> str:
    assert out.returncode == 0, out.stdout + out.stderr
    return out.stdout


def _records(project: Path, *args: str) -> list[dict]:
    return json.loads(_ok(cli(project, "report", "--format", "json", *args)))["records"]


# the planted regression: a sleep inside the timed call, so its p50 is at least this however busy the machine
PLANTED_MS = 3
# the fast settings' windows (0.01 s) are far shorter than /proc/stat counts well: judged with two ticks taken
# off each share, they are never flagged, so a busy machine cannot make the planted regression
# "not comparable"
WINDOW_S = 0.01


def test_compare_flags_a_planted_regression_and_keeps_every_run(tiny_project, tmp_path):
    env = install_slow_plugin(tmp_path)
    text = matrix_text(["onnxruntime", "slow_ort"], ["none"], ["fp32"], ["cpu"])
    assert f"window_s: {WINDOW_S}" in text and WINDOW_S < COUNTING_ERROR_S
    (tiny_project / "m.yaml").write_text(text)
    _ok(cli(tiny_project, "run", "m.yaml", "--label", "before", env={**env, "SLOW_ORT_DELAY_MS": "0"}))
    _ok(cli(tiny_project, "run", "m.yaml", "--force", "--label", "after",
            env={**env, "SLOW_ORT_DELAY_MS": str(PLANTED_MS)}))

    runs = _ok(cli(tiny_project, "runs", env=env))
    assert "before" in runs and "after" in runs
    before = {r["cell"]["backend"]: r for r in _records(tiny_project, "--run", "before")}
    latest = {r["cell"]["backend"]: r for r in _records(tiny_project)}
    # the tiny model's median call takes ~0.01 ms: under PLANTED_MS unless slowed 300-fold
    assert before["slow_ort"]["metrics"]["latency_ms"]["p50"] < PLANTED_MS \
        <= latest["slow_ort"]["metrics"]["latency_ms"]["p50"]
    assert before["slow_ort"]["run"] == 1 and latest["slow_ort"]["run"] == 2  # nothing was overwritten

    gate = cli(tiny_project, "compare", "before", "after", "--format", "json", env=env)
    assert gate.returncode == 1, gate.stdout + gate.stderr
    result = json.loads(gate.stdout)
    slowed = next(c for c in result["cells"] if c["key"] == "tiny/slow_ort/none/fp32/cpu")
    assert slowed["verdict"] == "worse"
    assert slowed["metrics"]["p50"]["verdict"] == "worse", slowed["metrics"]["p50"]
    assert slowed["metrics"]["p50"]["p_value"] < 0.05
    table = cli(tiny_project, "compare", "before", "after", "--threshold", "p50=100000%", "--threshold",
                "p99=100000%", "--threshold", "throughput=100000%", env=env)
    assert table.returncode == 0, table.stdout + table.stderr  # a threshold nothing exceeds: no gate
    assert "Mann-Whitney U" in table.stdout


# long enough windows and rounds for a median to mean something (the fast settings' windows are 0.01 s). ONNX
# Runtime cells: eager PyTorch's p99 on a 0.1 ms model moved 1.5 -> 4.2 ms between two unchanged runs in a
# fresh-clone CI (its tail is its own, not another process's)
STEADY = ("settings: {window_s: 0.05, min_rounds: 3, timing_budget_s: 0.4, warmup_iterations: 20, "
          "warmup_s: 0.1, batch_size: 8, timeout_s: 120, processes: 1}\n")


TIMED = ("p50", "p99", "throughput")
VALUES = {"p50": ("latency_ms", "p50"), "p99": ("latency_ms", "p99"), "throughput": ("throughput_sps",),
          "size": ("size_bytes",)}


def _compare(project: Path, base: str, new: str) -> dict:
    """`compare BASE NEW` as JSON; its exit code is 1 exactly when it lists a regression."""
    out = cli(project, "compare", base, new, "--format", "json")
    result = json.loads(out.stdout)
    assert out.returncode == (1 if result["regressions"] else 0), out.stdout + out.stderr
    return result


def _interference(change: dict) -> bool:
    return change["verdict"] == "not comparable" and "measured under interference" in change["why"]


def _key(record: dict) -> str:
    return "/".join(record["cell"][k] for k in ("model", "backend", "strategy", "precision", "target"))


def _stored(record: dict, path: tuple[str, ...]) -> float:
    value = record["metrics"]
    for key in path:
        value = value[key]
    return value


def test_two_runs_of_unchanged_cells_compare_unchanged(tiny_project):
    """What nothing changed cannot make worse: size and accuracy, the pairing of records and samples, a run
    against itself. A timed metric of two real runs may move with the machine (§3): not asserted."""
    text = matrix_text(["onnxruntime"], ["none", "ptq_dynamic"], ["fp32", "int8"], ["cpu"]).replace(
        FAST_SETTINGS, STEADY)
    (tiny_project / "m.yaml").write_text(text)
    _ok(cli(tiny_project, "run", "m.yaml"))
    _ok(cli(tiny_project, "run", "m.yaml", "--force"))
    runs = [{_key(r): r for r in _records(tiny_project, "--run", run)} for run in ("previous", "latest")]
    pair = _compare(tiny_project, "previous", "latest")
    assert [c["key"] for c in pair["cells"]] == sorted(runs[0]) == sorted(runs[1]) and len(runs[0]) == 2
    for cell in pair["cells"]:
        changes = cell["metrics"]
        assert {name: changes[name]["verdict"] for name in ("size", "accuracy")} == \
            {"size": "unchanged", "accuracy": "unchanged"}, cell
        for name, path in VALUES.items():  # each side's value is its own run's record
            stored = [_stored(run[cell["key"]], path) for run in runs]
            assert [changes[name]["base"], changes[name]["new"]] == stored, (name, cell)
        assert all(changes[m]["p_value"] is not None or _interference(changes[m]) for m in TIMED), cell
    assert all(regression["metric"] in TIMED for regression in pair["regressions"]), pair["regressions"]
    moved = json.loads(_ok(cli(tiny_project, "report", "--format", "json")))["reruns"]
    assert {model: [(r["run"], r["cells"]) for r in found] for model, found in moved.items()} == \
        {"tiny": [(1, 2)]}  # the first run timed the same 2 artifacts

    itself = _compare(tiny_project, "latest", "latest")
    assert itself["summary"]["worse"] == itself["summary"]["better"] == 0, itself
    for cell in itself["cells"]:
        for name, change in cell["metrics"].items():
            assert _interference(change) or (change["verdict"] == "unchanged" and change["change"] == 0), cell
            assert name not in TIMED or _interference(change) or change["p_value"] == 1.0, cell


def test_stores_of_two_hosts_merge_and_report_filters_by_host(onnx_project, tmp_path):
    tiny_project = onnx_project  # tiny.onnx: no process of the runs imports torch
    (tiny_project / "m.yaml").write_text(onnx_matrix_text(["tiny"], ["fp32"]).replace("[cpu]", "[cpu, cuda]"))
    for host in ("alpha", "beta"):
        _ok(cli(tiny_project, "run", "m.yaml", "--results", f"{host}.sqlite", env={"BENCH_MATRIX_HOST": host}))
    merged = tmp_path / "merged.sqlite"
    out = _ok(cli(tiny_project, "merge", "alpha.sqlite", "beta.sqlite", "--into", str(merged)))
    assert "alpha.sqlite: 1 run(s), 2 record(s) added" in out
    again = _ok(cli(tiny_project, "merge", "alpha.sqlite", "--into", str(merged)))
    assert "0 run(s), 0 record(s) added; 1 run(s) were already there" in again

    every = _records(tiny_project, "--results", str(merged))
    assert sorted((r["host"], r["cell"]["target"], r["status"]) for r in every) == [
        ("alpha", "cpu", "ok"), ("alpha", "cuda", "skipped"), ("beta", "cpu", "ok"), ("beta", "cuda", "skipped")]
    only = _records(tiny_project, "--results", str(merged), "--host", "beta")
    assert {r["host"] for r in only} == {"beta"} and len(only) == 2
    bad = cli(tiny_project, "report", "--results", str(merged), "--host", "gamma")
    assert bad.returncode == 2 and "no stored record matches --host gamma; the store holds hosts: alpha, beta" \
        in bad.stderr
    refused = cli(tiny_project, "compare", str(merged), "alpha.sqlite")
    assert refused.returncode == 2 and "holds records of 2 hosts (alpha, beta)" in refused.stderr


def test_a_store_of_the_previous_release_is_reported_and_extended(tiny_project):
    store = tiny_project / "old.sqlite"
    shutil.copy(FORMAT_1, store)
    before = store.read_bytes()
    old = _records(tiny_project, "--results", str(store))
    assert store.read_bytes() == before  # reading migrates in memory only
    assert sorted(r["status"] for r in old) == ["ok", "ok", "skipped", "skipped"]
    (tiny_project / "m.yaml").write_text(matrix_text(["pytorch"], ["none"], ["fp32"], ["cpu"]))
    _ok(cli(tiny_project, "run", "m.yaml", "--results", str(store), "--force", "--label", "new"))
    runs = _ok(cli(tiny_project, "runs", "--results", str(store)))
    assert "migrated from results format 1" in runs and "new" in runs
    assert len(_records(tiny_project, "--results", str(store), "--run", "1")) == 4  # the old records kept

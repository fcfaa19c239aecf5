"""End to end through the CLI with real runtimes: run, plan, report, backends, plugins, crash, kill, resume."""

from __future__ import annotations

import json
import os
import signal
import sqlite3
import subprocess
import time
from pathlib import Path

import numpy as np
import pytest

from bench_matrix.cell import Cell
from bench_matrix.store import ResultStore
from conftest import TESTS, TWO_PROCESSES, cli, install_slow_plugin, matrix_text, onnx_matrix_text, popen_cli
from polling import wait_for

pytestmark = pytest.mark.slow


def install_plugin(root: Path) -> dict[str, str]:
    """Install tests/plugin_crashy.py as distribution 'crashy-backend' the way pip would (dist-info + entry point)."""
    site = root / "site"
    dist = site / "crashy_backend-0.1.dist-info"
    dist.mkdir(parents=True)
    (dist / "METADATA").write_text("Metadata-Version: 2.1\nName: crashy-backend\nVersion: 0.1\n")
    (dist / "entry_points.txt").write_text("[bench_matrix.backends]\ncrashy = plugin_crashy:CrashyBackend\n"
                                           "broken = plugin_crashy:BrokenBackend\n")
    return {"PYTHONPATH": os.pathsep.join([str(site), str(TESTS), os.environ.get("PYTHONPATH", "")])}


def records(project: Path) -> dict[str, dict]:
    out = cli(project, "report", "--format", "json")
    assert out.returncode == 0, out.stderr
    return {"/".join(r["cell"][k] for k in ("backend", "strategy", "precision", "target")): r
            for r in json.loads(out.stdout)["records"]}


def test_run_small_matrix_and_report(tiny_project):
    unasked = "exclude: [{backend: torchscript, strategy: ptq_dynamic}]\n"
    (tiny_project / "m.yaml").write_text(matrix_text(["pytorch", "torchscript", "onnxruntime"],
                                                     ["none", "ptq_dynamic", "ptq_static"], ["fp32", "int8"],
                                                     ["cpu", "cuda"], unasked))
    plan = cli(tiny_project, "plan", "m.yaml")
    assert plan.returncode == 0, plan.stderr
    assert "6 will run" in plan.stdout and "3 will be skipped" in plan.stdout

    run = cli(tiny_project, "run", "m.yaml")
    assert run.returncode == 0, run.stdout + run.stderr
    assert "6 ok, 3 skipped, 0 failed" in run.stdout
    found = records(tiny_project)
    assert set(found) == {"pytorch/none/fp32/cpu", "torchscript/none/fp32/cpu",
                          "torchscript/ptq_static/int8/cpu", "onnxruntime/none/fp32/cpu",
                          "onnxruntime/ptq_dynamic/int8/cpu", "onnxruntime/ptq_static/int8/cpu",
                          "pytorch/none/fp32/cuda", "torchscript/none/fp32/cuda", "onnxruntime/none/fp32/cuda"}
    baseline = found["pytorch/none/fp32/cpu"]["metrics"]
    assert baseline["max_abs_diff_vs_baseline"] == 0.0
    for key, record in found.items():
        if key.endswith("cuda"):
            assert record["status"] == "skipped" and "GPU" in record["reason"]
            continue
        m = record["metrics"]
        assert record["status"] == "ok", record["reason"]
        assert set(record["env"]) >= {"host", "cpu", "cores", "python", "libraries"}
        assert m["latency_ms"]["n"] >= 5 and m["latency_ms"]["p50"] <= m["latency_ms"]["p99"]
        assert m["size_bytes"] > 0 and m["throughput_sps"] > 0 and m["peak_rss_mb"] > 0 and m["threads"] == 1
        assert m["test_samples"] == 24
        assert m["mse"] == pytest.approx(baseline["mse"], rel=0.5, abs=0.05)
        assert len(m["outputs_sha256"]) == 64 and "latency_ms_e2e" not in m and "gpu_name" not in m  # CPU cell
    digests = {key: r["metrics"]["outputs_sha256"] for key, r in found.items() if r["status"] == "ok"}
    assert digests["pytorch/none/fp32/cpu"] != digests["torchscript/ptq_static/int8/cpu"]  # int8 changes outputs
    assert found["onnxruntime/none/fp32/cpu"]["metrics"]["max_abs_diff_vs_baseline"] < 1e-4
    assert found["onnxruntime/none/fp32/cpu"]["metrics"]["session"]["providers"] == ["CPUExecutionProvider"]

    again = cli(tiny_project, "run", "m.yaml", "--backend", "onnxruntime")
    assert "0 ok" in again.stdout and "3 already stored" in again.stdout  # nothing finished is run again
    forced = cli(tiny_project, "run", "m.yaml", "--backend", "onnxruntime", "--strategy", "none", "--force")
    assert "1 ok" in forced.stdout
    assert records(tiny_project)["onnxruntime/none/fp32/cpu"]["metrics"]["artifact_cached"] is True

    table = cli(tiny_project, "report", "--out", str(tiny_project / "pages"))
    assert table.returncode == 0, table.stderr
    assert (tiny_project / "pages" / "index.md").is_file() and (tiny_project / "pages" / "tiny.md").is_file()


def test_plugin_backend_that_crashes_fails_only_its_cell(tiny_project):
    env = install_plugin(tiny_project)
    listing = cli(tiny_project, "backends", env=env)
    assert "crashy" in listing.stdout and "crashy-backend 0.1" in listing.stdout
    assert "cannot be loaded" in listing.stdout and "cannot be created: TypeError" in listing.stdout  # broken one

    (tiny_project / "m.yaml").write_text(matrix_text(["crashy", "pytorch"], ["none"], ["fp32"], ["cpu"]))
    run = cli(tiny_project, "run", "m.yaml", env=env)
    assert run.returncode == 0, run.stdout + run.stderr
    assert "1 ok, 0 skipped, 1 failed" in run.stdout
    found = records(tiny_project)
    assert found["pytorch/none/fp32/cpu"]["status"] == "ok"
    crashed = found["crashy/none/fp32/cpu"]
    assert crashed["status"] == "failed" and "killed by signal SIGABRT" in crashed["reason"]


def _wait_for_ok_record(db: Path, proc, timeout: float = 180) -> None:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        assert proc.poll() is None, proc.stdout.read()
        if db.is_file():
            try:
                with sqlite3.connect(db) as con:
                    if con.execute("SELECT count(*) FROM records WHERE status = 'ok'").fetchone()[0]:
                        return
            except sqlite3.OperationalError:  # the run has created the file but not yet its tables
                pass
        time.sleep(0.2)
    raise AssertionError("no cell finished in time")


def _workers_of(workspace: Path) -> list[int]:
    found = []
    for entry in Path("/proc").iterdir():
        try:
            cmd = (entry / "cmdline").read_bytes().replace(b"\0", b" ").decode()
        except (OSError, ValueError):
            continue
        if "bench_matrix.executors.child" in cmd and str(workspace) in cmd:
            found.append(int(entry.name))
    return found


# four ONNX models of one cell each (each model is measured on its own, in rounds) through
# tests/plugin_slow.py with no delay, its gate holding every session after the first:
# the run is certainly in its second cell, its measuring child waiting, when it is interrupted
INTERRUPTIBLE = onnx_matrix_text(["tiny", "twin", "third", "fourth"], ["fp32"]).replace(
    "[onnxruntime]", "[slow_ort]").replace(*TWO_PROCESSES)  # a cell's 2 processes pass the gate together


def _start_gated_run(project: Path) -> tuple[subprocess.Popen, dict[str, str]]:
    """`run` of INTERRUPTIBLE once its first cell is stored and its second waits at the gate; the env of a run
    without the gate."""
    gate = project / "gate"
    gate.mkdir()
    env = {**install_slow_plugin(project), "SLOW_ORT_DELAY_MS": "0"}
    (project / "m.yaml").write_text(INTERRUPTIBLE)
    proc = popen_cli(project, "run", "m.yaml", env={**env, "SLOW_ORT_GATE": str(gate)})
    _wait_for_ok_record(project / "ws" / "results.sqlite", proc)
    wait_for(lambda: list(gate.glob("waiting-*")), "the second cell waiting at the gate")
    return proc, env


def test_killed_run_keeps_finished_cells_and_resumes(onnx_project):
    db = onnx_project / "ws" / "results.sqlite"
    proc, env = _start_gated_run(onnx_project)
    assert _workers_of(onnx_project / "ws")  # the second cell's, at the gate
    proc.kill()  # SIGKILL: no chance to clean up
    proc.wait()
    wait_for(lambda: _workers_of(onnx_project / "ws") == [], "children dying with their parent", timeout_s=30)
    with sqlite3.connect(db) as con:
        kept = dict(con.execute("SELECT key, finished_at FROM records WHERE status = 'ok'").fetchall())
    assert len(kept) == 1

    rerun = cli(onnx_project, "run", "m.yaml", env=env)
    assert rerun.returncode == 0, rerun.stdout + rerun.stderr
    assert "3 ok" in rerun.stdout and "1 already stored" in rerun.stdout
    with sqlite3.connect(db) as con:
        after = dict(con.execute("SELECT key, finished_at FROM records WHERE status = 'ok'").fetchall())
    assert len(after) == 4 and all(after[k] == v for k, v in kept.items())  # finished cells were not re-run


def test_ctrl_c_stops_cleanly_with_exit_130(onnx_project):
    proc, _ = _start_gated_run(onnx_project)
    proc.send_signal(signal.SIGINT)
    output, _ = proc.communicate(timeout=60)
    assert proc.returncode == 130
    assert "interrupted" in output and "run the same command again to resume" in output
    assert "Traceback" not in output
    assert _workers_of(onnx_project / "ws") == []


def test_plan_judges_strategy_options_and_filters_are_checked(tiny_project):
    extra = "strategies:\n  int8_io: {kind: ptq_static, io: int8}\n  entropy: {kind: ptq_static, method: entropy}\n"
    (tiny_project / "m.yaml").write_text(matrix_text(["torchscript", "onnxruntime"], ["int8_io", "entropy"],
                                                     ["int8"], ["cpu"], extra))
    plan = cli(tiny_project, "plan", "m.yaml")
    assert plan.returncode == 0, plan.stderr
    assert "0 will run" in plan.stdout and "4 not valid" in plan.stdout
    assert "io: int8 is not available with this backend" in plan.stdout
    assert "calibrates with minmax or percentile, not 'entropy'" in plan.stdout

    typo = cli(tiny_project, "run", "m.yaml", "--backend", "onnxruntme")
    assert typo.returncode == 2 and "Traceback" not in typo.stderr
    assert "--backend onnxruntme: no cell of the matrix has this backend" in typo.stderr
    assert "did you mean 'onnxruntime'?" in typo.stderr


def test_user_errors_exit_2_without_traceback(tiny_project):
    (tiny_project / "m.yaml").write_text(matrix_text(["pytorch"], ["none"], ["fp32"], ["cpu"]).replace(
        "npz: data.npz", "npz: missing.npz"))
    out = cli(tiny_project, "run", "m.yaml")
    assert out.returncode == 2 and "Traceback" not in out.stderr
    assert "m.yaml:3: dataset.npz: dataset file not found" in out.stderr

    np_bad = tiny_project / "bad.npz"
    import numpy as np

    np.savez(np_bad, images=np.zeros((10, 4, 4, 3)))
    (tiny_project / "m.yaml").write_text(matrix_text(["pytorch"], ["none"], ["fp32"], ["cpu"]).replace(
        "npz: data.npz", "npz: bad.npz"))
    out = cli(tiny_project, "run", "m.yaml")
    assert out.returncode == 2 and "Traceback" not in out.stderr
    assert "missing array 'y'" in out.stderr and "it has: images" in out.stderr

    missing = cli(tiny_project, "run", "nope.yaml")
    assert missing.returncode == 2 and "nope.yaml: file not found" in missing.stderr


def test_a_models_cells_are_timed_in_rounds_with_a_paired_speedup(onnx_project):
    (onnx_project / "m.yaml").write_text(onnx_matrix_text(["tiny"], ["fp32", "fp16"]).replace(
        "min_rounds: 2, timing_budget_s: 0.05", "min_rounds: 3, timing_budget_s: 1").replace(*TWO_PROCESSES))
    run = cli(onnx_project, "run", "m.yaml")
    assert run.returncode == 0, run.stdout + run.stderr
    found = records(onnx_project)
    base, half = found["onnxruntime/none/fp32/cpu"]["metrics"], found["onnxruntime/none/fp16/cpu"]["metrics"]
    assert "speedup" not in base and base["rounds"]["rounds"] >= 3  # the baseline is paired against
    kept = {"latency_ms", "throughput_sps", "throughput_batches", "batch_size", "peak_rss_mb", "size_bytes",
            "size_gzip_bytes", "files", "params", "convert_s", "artifact_cached", "load_s", "threads", "session",
            "test_samples", "interference", "timing_window", "cpu_affinity", "outputs_sha256",
            "max_abs_diff_vs_baseline", "cosine_similarity", "snr_db"}  # the fields before the rounds...
    assert kept | {"speedup", "rounds", "throughput_ci"} <= set(half)  # ... and the new ones
    assert not {"latency_attempts", "latency_stability", "latency_passes_p50"} & set(half)  # retired
    ratio = half["speedup"]
    # paired over the rounds both had clean: a round a loaded machine disturbed leaves the pair, not the run
    assert 2 <= ratio["rounds"] <= half["timing_window"]["rounds"]
    assert ratio["ci"][0] <= ratio["value"] <= ratio["ci"][1]
    assert half["rounds"]["stop"] in ("width", "budget") and half["timing_window"]["rounds"] >= 3
    assert half["rounds"]["processes"] == 2 and half["rounds"]["model_spread"] is not None
    assert half["rounds"]["visits"] == base["rounds"]["visits"] == 1.0  # one cell paired: the baseline √1 times
    logs = onnx_project / "ws" / "logs"
    assert (logs / "tiny__onnxruntime__none__fp16__cpu.log").exists()
    assert (logs / "tiny__onnxruntime__none__fp16__cpu.2.log").exists()  # each process logs apart
    low, high = half["latency_ms"]["p50_ci"]
    assert low <= half["latency_ms"]["p50"] <= high and half["throughput_sps"] > 0
    assert f"{ratio['value']:.3g}× ±" in run.stdout  # the progress line
    store = ResultStore(onnx_project / "ws" / "results.sqlite", readonly=True)
    (record,) = [r for r in store.records()
                 if r.cell == Cell("tiny", "onnx", "onnxruntime", "none", "fp16", "cpu")]
    kept = store.samples(record)
    store.close()
    assert len(kept) == half["latency_ms"]["n"]  # the raw samples are every kept window's
    assert float(np.median(kept)) == pytest.approx(half["latency_ms"]["p50"], rel=1e-5)
    table = cli(onnx_project, "report").stdout
    assert f"{ratio['value']:.2f}× ±{ratio['ci_half']:.1%}" in table

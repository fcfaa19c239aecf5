"""Harness overhead: bench-matrix's reported p50 for the ONNX Runtime fp32 PilotNet cell vs a bare loop.

Both sides time the same .onnx artifact with the same session options, thread count, inputs and warm-up (the
harness in its rounds of windows and processes as the defaults set them, the bare loop 200 calls and 2 s at
least), on the same CPU core (this process pins itself; the CLI and its cell processes inherit the
affinity). Rounds alternate (harness, bare, harness, ...) so machine noise hits both; the median of the
per-round ratios and the ratio of the medians are printed. Target: within 2 %.

    .venv/bin/python benchmarks/harness_overhead.py [--rounds 9] [--cpu N] [--workdir DIR]
"""

from __future__ import annotations

import argparse
import json
import os
import sqlite3
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

MATRIX = """\
models:
  - {name: pilotnet, framework: pytorch, builtin: pilotnet, training: {epochs: 1}}
dataset: {builtin: driving, samples: 400, circuits: 4, seed: 0}
axes: {backend: [onnxruntime], strategy: [none], precision: [fp32], target: [cpu]}
settings: {threads: 1, warmup_iterations: 20, warmup_s: 0.5, min_rounds: 10, timing_budget_s: 2}
"""


def harness_p50(workdir: Path) -> tuple[float, Path]:
    """Run the cell through the CLI (its own processes) and read the p50 it stored."""
    subprocess.run([sys.executable, "-m", "bench_matrix.cli", "--workspace", str(workdir / "ws"), "run",
                    str(workdir / "matrix.yaml"), "--force"], check=True, capture_output=True, cwd=workdir)
    with sqlite3.connect(workdir / "ws" / "results.sqlite") as db:
        metrics, artifact = db.execute("SELECT metrics, artifact_path FROM records WHERE status = 'ok' "
                                       "ORDER BY id DESC").fetchone()  # this run's: every run is kept
    return json.loads(metrics)["latency_ms"]["p50"], Path(artifact)


def bare_p50(artifact: Path, inputs: list[np.ndarray], threads: int = 1) -> float:
    """What a careful user would write: one session, fixed threads, warm-up, perf_counter_ns per call."""
    import onnxruntime as ort

    options = ort.SessionOptions()
    options.intra_op_num_threads, options.inter_op_num_threads = threads, 1
    options.execution_mode = ort.ExecutionMode.ORT_SEQUENTIAL
    options.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
    session = ort.InferenceSession(str(artifact / "model.onnx"), options, providers=["CPUExecutionProvider"])
    name = session.get_inputs()[0].name
    feeds = [{name: x} for x in inputs]
    begin = time.perf_counter()
    i = 0
    while i < 20 or time.perf_counter() - begin < 0.5:
        session.run(None, feeds[i % len(feeds)])
        i += 1
    clock, durations, begin = time.perf_counter_ns, [], time.perf_counter_ns()
    while len(durations) < 200 or clock() - begin < 2e9:
        feed = feeds[len(durations) % len(feeds)]
        t0 = clock()
        session.run(None, feed)
        durations.append(clock() - t0)
    return float(np.percentile(np.asarray(durations) / 1e6, 50))


def test_inputs(workdir: Path, count: int = 16) -> list[np.ndarray]:
    """The same first test samples the cell times, preprocessed the same way (pixels / 255, NCHW)."""
    split = next((workdir / "ws" / "cache" / "datasets").glob("*/test__x.npy"))
    images = np.load(split)[:count].astype(np.float32) / 255.0
    return [np.ascontiguousarray(img.transpose(2, 0, 1)[None]) for img in images]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rounds", type=int, default=9)
    parser.add_argument("--cpu", type=int, default=max(os.sched_getaffinity(0)),
                        help="core both sides run on (default: the highest-numbered usable core)")
    parser.add_argument("--workdir", type=Path)
    args = parser.parse_args()
    os.sched_setaffinity(0, {args.cpu})
    workdir = args.workdir or Path(tempfile.mkdtemp(prefix="bench-matrix-overhead-"))
    workdir.mkdir(parents=True, exist_ok=True)
    (workdir / "matrix.yaml").write_text(MATRIX)
    print(f"workdir {workdir}: preparing (dataset, 1-epoch PilotNet, ONNX export)...", flush=True)
    _, artifact = harness_p50(workdir)
    inputs = test_inputs(workdir)
    harness, bare = [], []
    for r in range(args.rounds):
        h, _ = harness_p50(workdir)
        b = bare_p50(artifact, inputs)
        harness.append(h)
        bare.append(b)
        print(f"round {r + 1}: bench-matrix p50 {h:.4f} ms   bare loop p50 {b:.4f} ms   ratio {h / b:.4f}", flush=True)
    ratio = statistics.median(harness) / statistics.median(bare)
    per_round = statistics.median(h / b for h, b in zip(harness, bare))
    print(f"\nmedian p50 on cpu {args.cpu}: bench-matrix {statistics.median(harness):.4f} ms, "
          f"bare loop {statistics.median(bare):.4f} ms")
    print(f"ratio of medians bench-matrix / bare = {ratio:.4f} ({(ratio - 1) * 100:+.2f} %); "
          f"median of per-round ratios = {per_round:.4f} ({(per_round - 1) * 100:+.2f} %)")
    print(f"target within ±2 %: {'met' if abs(ratio - 1) <= 0.02 else 'NOT met'}")


if __name__ == "__main__":
    main()

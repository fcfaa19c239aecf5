"""How often `compare --remeasure` raises a false alarm on unchanged artifacts and catches a +10 % regression,
quiet and with a CPU-bound process on the other core (docs/results.md §2, --remeasure).

Ten models, each a dense ONNX network; run "base" with one width, run "slow" with a width calibrated here to
be about 10 % slower (timed side by side in this process first). Each comparison remeasures the ten twins in the
same rounds: `compare base base` gives ten unchanged pairs, `compare base slow` ten +10 % ones; --repeats
comparisons of each. The last line: `unchanged: A false alarms of N; +10 %: C caught of N; not comparable: U`
(a false alarm: worse or better; not comparable: twins the rounds could not pair, which fail no gate).
Targets: at most 1 false alarm in 20 unchanged pairs, +10 % caught in at least 19 of 20.

    .venv/bin/python benchmarks/gate_rates.py [--repeats 2] [--hog] [--workdir DIR]
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

MODELS = 10
BASE_WIDTH = 256
SETTINGS = "settings: {threads: 1, window_s: 0.05, timing_budget_s: 2, processes: 2, batch_size: 8}\n"


def dense(hidden: int) -> bytes:
    """(N,3,16,16) -> (N,2) through three dense layers of width `hidden`."""
    from onnx import TensorProto, helper, numpy_helper

    rng = np.random.default_rng(0)
    sizes = [768, hidden, hidden, hidden, 2]
    weights = [numpy_helper.from_array((rng.standard_normal(s) / np.sqrt(s[0])).astype(np.float32), f"W{i}")
               for i, s in enumerate(zip(sizes, sizes[1:]))]
    nodes = [helper.make_node("Flatten", ["X"], ["H0"])]
    for i in range(len(weights)):
        last = i == len(weights) - 1
        nodes += [helper.make_node("MatMul", [f"H{i}", f"W{i}"], [f"M{i}"]),
                  helper.make_node("Identity" if last else "Relu", [f"M{i}"], ["Y" if last else f"H{i + 1}"])]
    tensor = helper.make_tensor_value_info
    graph = helper.make_graph(nodes, "dense", [tensor("X", TensorProto.FLOAT, ["N", 3, 16, 16])],
                              [tensor("Y", TensorProto.FLOAT, ["N", 2])], weights)
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)], ir_version=8)
    return model.SerializeToString()


def ratio(slow: int, seconds: float = 3.0) -> float:
    """The median time of width `slow` over BASE_WIDTH's, interleaved in this process (one thread)."""
    import onnxruntime as ort

    options = ort.SessionOptions()
    options.intra_op_num_threads = 1
    sessions = [ort.InferenceSession(dense(w), options) for w in (BASE_WIDTH, slow)]
    feed = {"X": np.random.default_rng(1).standard_normal((1, 3, 16, 16)).astype(np.float32)}
    times: list[list[float]] = [[], []]
    end = time.perf_counter() + seconds
    while time.perf_counter() < end:
        for k, session in enumerate(sessions):
            start = time.perf_counter_ns()
            session.run(None, feed)
            times[k].append(time.perf_counter_ns() - start)
    return statistics.median(times[1]) / statistics.median(times[0])


def calibrated(target: float = 1.10) -> tuple[int, float]:
    """The width whose time is about `target` times BASE_WIDTH's, and its measured ratio."""
    width = int(BASE_WIDTH * target ** 0.5)
    for _ in range(6):
        found = ratio(width)
        if abs(found - target) < 0.01:
            break
        width = max(BASE_WIDTH + 1, int(width * (target / found) ** 0.5))
    return width, ratio(width)


def project(workdir: Path, slow: int) -> None:
    """The two runs' stores: "base" and "slow", every model's cell."""
    rng = np.random.default_rng(0)
    np.savez(workdir / "data.npz", x=rng.standard_normal((64, 3, 16, 16)).astype(np.float32),
             y=rng.standard_normal((64, 2)).astype(np.float32))
    models = "".join(f"  - {{name: m{k}, framework: onnx, file: dense.onnx}}\n" for k in range(MODELS))
    (workdir / "m.yaml").write_text(
        "models:\n" + models
        + "dataset: {npz: data.npz, split: {train: 0.5, calibration: 0.25, test: 0.25}}\n"
        "axes: {backend: [onnxruntime], strategy: [none], precision: [fp32], target: [cpu]}\n" + SETTINGS)
    for label, width in (("base", BASE_WIDTH), ("slow", slow)):
        (workdir / "dense.onnx").write_bytes(dense(width))
        cli(workdir, "run", "m.yaml", "--force", "--label", label)


def cli(workdir: Path, *args: str) -> subprocess.CompletedProcess:
    command = [sys.executable, "-m", "bench_matrix.cli", "--workspace", str(workdir / "ws"), *args]
    done = subprocess.run(command, cwd=workdir, capture_output=True, text=True)
    if done.returncode not in (0, 1):
        raise SystemExit(f"bench-matrix {' '.join(args)} failed:\n{done.stdout}\n{done.stderr}")
    return done


def verdicts(workdir: Path, new: str) -> list[tuple[str, float]]:
    """Each remeasured model's p50 verdict and change, base against `new`."""
    found = json.loads(cli(workdir, "compare", "base", new, "--remeasure", "--matrix", "m.yaml",
                           "--format", "json").stdout)
    return [(c["metrics"]["p50"]["verdict"], c["metrics"]["p50"]["change"]) for c in found["cells"]]


def shown(verdict: str, change: float | None, expected: str) -> str:
    """A pair's change, marked where its verdict is not the one expected."""
    if change is None:
        return "n/c"
    return f"{change:+.1%}" + ("" if verdict == expected else "!")


def hog() -> subprocess.Popen:
    """A CPU-bound process on the lowest usable CPU (the cells are pinned to the highest)."""
    proc = subprocess.Popen([sys.executable, "-c", "while True: pass"])
    os.sched_setaffinity(proc.pid, {min(os.sched_getaffinity(0))})
    return proc


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--repeats", type=int, default=2, help="comparisons of each kind (10 pairs each)")
    parser.add_argument("--hog", action="store_true", help="a CPU-bound process on the other core throughout")
    parser.add_argument("--workdir", type=Path)
    args = parser.parse_args()
    workdir = args.workdir or Path(tempfile.mkdtemp(prefix="bm-gate-"))
    workdir.mkdir(parents=True, exist_ok=True)
    width, found = calibrated()
    print(f"slow width {width} vs {BASE_WIDTH}: {found:.3f} times the time (in this process, quiet)")
    project(workdir, width)
    competitor = hog() if args.hog else None
    try:
        same = [v for _ in range(args.repeats) for v in verdicts(workdir, "base")]
        slower = [v for _ in range(args.repeats) for v in verdicts(workdir, "slow")]
    finally:
        if competitor is not None:
            competitor.kill()
    changes = [c for _, c in slower if c is not None]
    print(f"unchanged pairs' changes: {', '.join(shown(v, c, 'unchanged') for v, c in same)}")
    print(f"+10 % pairs' changes: {', '.join(shown(v, c, 'worse') for v, c in slower)} "
          f"(median {statistics.median(changes):+.1%}; ! judged otherwise, n/c: not comparable)")
    alarms = sum(v in ("worse", "better") for v, _ in same)
    caught = sum(v == "worse" for v, _ in slower)
    unpaired = sum(c is None for _, c in same + slower)
    print(f"{'under --hog' if args.hog else 'quiet'}: unchanged: {alarms} false alarms of {len(same)}; "
          f"+10 %: {caught} caught of {len(slower)}; not comparable: {unpaired}")


if __name__ == "__main__":
    main()

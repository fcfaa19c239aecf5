"""Interference: the same cells measured quiet, under a second concurrent `bench-matrix run`, and under
CPU-bound competitors; how far each stored p50 and p99 is from the quiet figures, and whether it was flagged.

Conditions, in this order, each a `run --force` of the same seven cells in one workspace (PilotNet trained
1 epoch, in PyTorch through PyTorch, TorchScript and ONNX Runtime at fp32 and dynamic int8, and in Keras
through TensorFlow and TFLite at fp32):
  quiet        nothing else runs (the reference)
  second-run   a second `bench-matrix run` of the same matrix in a fresh workspace starts just before (it
               trains, converts and measures; the machine's timing lock lets only one of them time at once)
  competitor   `python -c "while True: pass"` on every usable CPU (--competitors to change how many)
  quiet-again  nothing else runs: no cell may be flagged
Target (issue 14): every cell whose p99 moved by more than 20 % is either re-measured back within 5 % of quiet
or flagged; no quiet cell is flagged. "Quiet" for a cell is whichever quiet run gave it the lower p50
(interference only adds time), leaving out a quiet run during which other work used the machine. The last
tables give, by condition, the interference figures of every timed
attempt and the p50's confidence-interval width: what the limits and the ci_rel_width default in
docs/metrics.md §5 are chosen from; every record's metrics (each attempt's figures included) are kept in
WORKDIR/metrics-CONDITION.json. Column "flag": flag = flagged for interference, ~ = its kept latency
window drifted (unsteady, marked ~ in reports, not flagged), no = neither.

    .venv/bin/python benchmarks/interference.py [--workdir DIR] [--competitors N]
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path
from typing import Any

from bench_matrix.measure.interference import Limits
from bench_matrix.store import ResultStore

MATRIX = """\
models:
  - {name: pilotnet, framework: pytorch, builtin: pilotnet, training: {epochs: 1}}
  - {name: pilotnet-tf, framework: tensorflow, builtin: pilotnet, training: {epochs: 1}}
dataset: {builtin: driving, samples: 400, circuits: 4, seed: 0}
axes: {backend: [pytorch, torchscript, onnxruntime, tensorflow, tflite], strategy: [none, ptq_dynamic],
       precision: [fp32, int8], target: [cpu]}
exclude:
  - {model: pilotnet-tf, backend: onnxruntime}
  - {model: pilotnet-tf, strategy: ptq_dynamic}
settings: {threads: 1, warmup_iterations: 20, warmup_s: 0.5, min_iterations: 200, min_time_s: 1.5,
           throughput_time_s: 0.5}
"""
FIGURES = ("other_share", "machine_share", "steal_share", "preemptions_per_s")
MOVED, BACK = 0.20, 0.05  # the target: moved by more than MOVED must come back within BACK, or be flagged


def cli(workspace: Path, *args: str) -> list[str]:
    """The command line of `bench-matrix --workspace WORKSPACE ARGS...`."""
    return [sys.executable, "-m", "bench_matrix.cli", "--workspace", str(workspace), *args]


def measure(workdir: Path) -> dict[str, dict[str, Any]]:
    """`run --force` in the measured workspace; every stored ok record's metrics, by cell label."""
    subprocess.run(cli(workdir / "ws", "run", "matrix.yaml", "--force"), cwd=workdir, check=True,
                   capture_output=True)
    store = ResultStore(workdir / "ws" / "results.sqlite", readonly=True)
    try:
        return {f"{r.cell.model} · {r.cell.label}": r.metrics.to_json() for r in store.records() if r.status == "ok"}
    finally:
        store.close()


def quiet(workdir: Path, _: argparse.Namespace) -> dict[str, dict[str, Any]]:
    return measure(workdir)


def second_run(workdir: Path, _: argparse.Namespace) -> dict[str, dict[str, Any]]:
    """A second run of the matrix in a fresh workspace starts first; both finish."""
    other = Path(tempfile.mkdtemp(prefix="second-", dir=workdir))
    second = subprocess.Popen(cli(other, "run", "matrix.yaml"), cwd=workdir, stdout=subprocess.DEVNULL,
                              stderr=subprocess.DEVNULL)
    try:
        return measure(workdir)
    finally:
        if second.wait() != 0:
            print(f"  (the second run failed: see {other}/logs)", flush=True)


def competitor(workdir: Path, args: argparse.Namespace) -> dict[str, dict[str, Any]]:
    """CPU-bound processes, one pinned to each of the highest usable CPUs, while the cells are measured."""
    cpus = sorted(os.sched_getaffinity(0), reverse=True)[:args.competitors]
    procs = [subprocess.Popen([sys.executable, "-c", "while True: pass"]) for _ in cpus]
    for proc, cpu in zip(procs, cpus):
        os.sched_setaffinity(proc.pid, {cpu})
    try:
        return measure(workdir)
    finally:
        for proc in procs:
            proc.kill()
            proc.wait()


CONDITIONS = {"quiet": quiet, "second-run": second_run, "competitor": competitor, "quiet-again": quiet}


def attempts(metrics: dict[str, Any]) -> list[dict[str, Any]]:
    """Every timed attempt of every phase of a record."""
    phases = metrics["interference"]["phases"].values()
    return [attempt for phase in phases for attempt in phase["attempts"]]


def mark(metrics: dict[str, Any]) -> str:
    """"flag": flagged for interference; "~": the kept latency attempt drifted (unsteady, marked ~); "no"."""
    if metrics["interference"]["flagged"]:
        return "flag"
    latency = metrics["interference"]["phases"]["latency"]
    return "~" if latency["attempts"][latency["kept"]]["unsteady"] else "no"


def verdict(condition: str, marked: str, p99_moved: float, noisy: bool) -> str:
    """How the cell meets the target (MISSED and FALSE FLAG do not); `noisy`: a quiet run that was not
    quiet."""
    if condition.startswith("quiet"):
        flagged = "flagged (this run was not quiet)" if noisy else "FALSE FLAG"
        return {"flag": flagged, "~": "ok (unsteady ~, not flagged)"}.get(marked, "ok")
    if marked == "flag":
        return "ok (flagged)"
    if abs(p99_moved) <= BACK:
        return "ok (within 5 %)"
    if abs(p99_moved) <= MOVED:
        return "ok (moved < 20 %)"
    return "ok (unsteady ~, not flagged)" if marked == "~" else "MISSED"


def quiet_reference(results: dict[str, dict[str, dict[str, Any]]], noisy: dict[str, str]
                    ) -> dict[str, dict[str, Any]]:
    """Each cell's latency figures from the quiet run (a really quiet one, if any) that gave it the lower
    p50."""
    quiet = [condition for condition in results if condition.startswith("quiet")]
    runs = [results[c] for c in quiet if c not in noisy] or [results[c] for c in quiet]
    return {label: min((run[label]["latency_ms"] for run in runs if label in run), key=lambda lat: lat["p50"])
            for label in runs[0]}


def cell_table(condition: str, measured: dict[str, dict[str, Any]], reference: dict[str, dict[str, Any]],
               noisy: bool) -> list[str]:
    """One line per cell: stored p50 and p99 against quiet, the first attempt's p99, attempts, verdict."""
    lines = []
    for label, metrics in sorted(measured.items()):
        base, latency = reference[label], metrics["latency_ms"]
        first = metrics["interference"]["phases"]["latency"]["attempts"][0]["p99_ms"]
        d50, d99 = latency["p50"] / base["p50"] - 1, latency["p99"] / base["p99"] - 1
        marked = mark(metrics)
        lines.append(f"{condition:<12} {label:<44} {latency['p50']:8.4f} {d50:+7.1%} {latency['p99']:8.4f} "
                     f"{d99:+7.1%} {first / base['p99'] - 1:+8.1%} {metrics['latency_attempts']:3d} "
                     f"{marked:>4}  {verdict(condition, marked, d99, noisy)}")
    return lines


def figure_table(results: dict[str, dict[str, dict[str, Any]]]) -> list[str]:
    """min / median / max of each interference figure over every timed attempt of every cell, by condition."""
    lines = [f"{'condition':<12} {'figure':<18} {'attempts':>8} {'min':>9} {'median':>9} {'max':>9}"]
    for condition, measured in results.items():
        every = [a for metrics in measured.values() for a in attempts(metrics)]
        for figure in FIGURES:
            values = [float(a[figure]) for a in every]
            lines.append(f"{condition:<12} {figure:<18} {len(values):8d} {min(values):9.4f} "
                         f"{statistics.median(values):9.4f} {max(values):9.4f}")
    return lines


def width_table(results: dict[str, dict[str, dict[str, Any]]]) -> list[str]:
    """min / median / max over the cells of p50_ci_rel and of the calls timed, by condition."""
    lines = [f"{'condition':<12} {'p50_ci_rel min':>14} {'median':>9} {'max':>9} {'n min':>7} {'max':>7}"]
    for condition, measured in results.items():
        widths = [m["latency_ms"]["p50_ci_rel"] for m in measured.values()]
        calls = [m["latency_ms"]["n"] for m in measured.values()]
        middle = statistics.median(widths)
        lines.append(f"{condition:<12} {min(widths):14.4f} {middle:9.4f} {max(widths):9.4f} {min(calls):7d} "
                     f"{max(calls):7d}")
    return lines


def not_quiet(results: dict[str, dict[str, dict[str, Any]]]) -> dict[str, str]:
    """The quiet runs during which other work used the machine (median figure above its limit), with a
    note."""
    limits, notes = Limits(), {}
    for condition, measured in results.items():
        every = [a for metrics in measured.values() for a in attempts(metrics)]
        machine = statistics.median(a["machine_share"] for a in every)
        other = statistics.median(a["other_share"] for a in every)
        if condition.startswith("quiet") and (machine > limits.machine_share or other > limits.other_share):
            notes[condition] = (f"note: the {condition} run was not quiet (median machine_share "
                                f"{machine:.2f}, other_share {other:.2f}): other work used this machine, so "
                                f"its flags are right and it is not the reference; run again on a quiet "
                                f"machine")
    return notes


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--workdir", type=Path)
    parser.add_argument("--competitors", type=int, default=len(os.sched_getaffinity(0)),
                        help="CPU-bound processes in the competitor condition (default: one per usable CPU)")
    args = parser.parse_args()
    workdir = args.workdir or Path(tempfile.mkdtemp(prefix="bench-matrix-interference-"))
    workdir.mkdir(parents=True, exist_ok=True)
    (workdir / "matrix.yaml").write_text(MATRIX)
    print(f"workdir {workdir}: preparing (dataset, 1-epoch PilotNet, conversions)...", flush=True)
    subprocess.run(cli(workdir / "ws", "run", "matrix.yaml"), cwd=workdir, check=True,
                   capture_output=True)
    results: dict[str, dict[str, dict[str, Any]]] = {}
    for condition, run in CONDITIONS.items():
        print(f"measuring: {condition}", flush=True)
        results[condition] = run(workdir, args)
        (workdir / f"metrics-{condition}.json").write_text(json.dumps(results[condition], indent=1))
    print(f"\nlimits: {Limits()}\n")
    print(f"{'condition':<12} {'cell':<44} {'p50 ms':>8} {'Δp50':>7} {'p99 ms':>8} {'Δp99':>7} "
          f"{'1st Δp99':>8} {'att':>3} {'flag':>4}  verdict (Δ against quiet; 1st: first attempt)")
    noisy = not_quiet(results)
    reference = quiet_reference(results, noisy)
    lines = [line for condition, measured in results.items()
             for line in cell_table(condition, measured, reference, condition in noisy)]
    print("\n".join(lines))
    print("\ninterference figures of every timed attempt (latency and throughput phases):")
    print("\n".join(figure_table(results)))
    print("\nwidth of the p50's 95 % interval, (hi - lo) / p50, of the kept latency attempt:")
    print("\n".join(width_table(results)))
    failures = [line for line in lines if "MISSED" in line or "FALSE FLAG" in line]
    print("", *noisy.values(), sep="\n")
    print(f"target (moved > 20 % => back within 5 % or flagged; no quiet cell flagged): "
          f"{'met' if not failures else f'NOT met ({len(failures)} cell(s))'}")


if __name__ == "__main__":
    main()

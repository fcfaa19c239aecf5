"""Reproducibility: a matrix run twice with `--force`; how far each cell's speed-up and p50 moved between the
two runs, and whether the first run's interval covered the second's p50 (docs/metrics.md §5).

Per cell: both p50s, both speed-ups (paired by round against the baseline) and their difference, whether run
2's p50 lies inside run 1's 95 % interval, and whether either run marked it (~: disturbed or too wide). Then
how the machine's speed moved between the runs (the median p50 ratio), which no interval from one run can
see, and how many intervals hold run 2's p50 with that move taken out. The last line: `speed-up difference
median X %, max Y %; p50 CI coverage Z %; flagged N of M; timing T s` (T: the seconds both runs spent in
rounds). With --hog, a CPU-bound process runs on the other core during run 2.
Then the answers, judged by the report's own code against the matrix's requirements: per model and target,
both runs' recommended cells (and whether each run tells it from its runner-up) and verdicts, and a last line
`answers same N of M` (the same recommended cell and every cell's verdict the same in both runs).
Targets on a quiet 2-core VM: median <= 2 %, max <= 5 %, coverage >= 90 %, at most 10 % of cells marked;
under --hog, every cell within 5 % of its quiet speed-up, or marked; the answers the same in every pair where
the runs call the recommendation distinguishable.

    .venv/bin/python benchmarks/reproducibility.py [--matrix M.yaml] [--hog] [--workdir DIR]
"""

from __future__ import annotations

import argparse
import os
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

from bench_matrix.report import load_judged
from bench_matrix.report.analysis.judging import Judging
from bench_matrix.report.analysis.summary import ModelSummary, disturbed_phases, wide_phases
from bench_matrix.store import CellRecord, ResultStore

# the PilotNet TensorFlow variant through TensorFlow (its baseline), TFLite, ONNX Runtime and OpenVINO
MATRIX = """\
models:
  - {name: pilotnet-tf, framework: tensorflow, builtin: pilotnet, training: {epochs: 2}}
dataset: {builtin: driving, samples: 1000, circuits: 10, seed: 0}
strategies:
  ptq_static: {kind: ptq_static, calibration_samples: 100}
axes: {backend: [tensorflow, tflite, onnxruntime, openvino], strategy: [none, ptq_dynamic, ptq_static],
       precision: [fp32, fp16, int8], target: [cpu]}
requirements: {max_drop: 5%, p50_ms: 25, p99_ms: 50}
settings: {threads: 1}
"""


def run(workdir: Path, matrix: Path, label: str) -> list[CellRecord]:
    """`run --force` of the matrix into the run's own store; its ok records."""
    store = workdir / f"{label}.sqlite"
    subprocess.run([sys.executable, "-m", "bench_matrix.cli", "--workspace", str(workdir / "ws"), "run",
                    str(matrix), "--force", "--results", str(store), "--label", label], check=True,
                   cwd=workdir, stdout=subprocess.DEVNULL)
    return [r for r in ResultStore(store, readonly=True).records() if r.status == "ok"]


def hog() -> subprocess.Popen:
    """A CPU-bound process on the usable CPU the cells are not pinned to (the lowest one)."""
    proc = subprocess.Popen([sys.executable, "-c", "while True: pass"])
    os.sched_setaffinity(proc.pid, {min(os.sched_getaffinity(0))})
    return proc


def speedup(record: CellRecord) -> float | None:
    found = record.metrics.speedup
    return found.value if found is not None else None


def marked(record: CellRecord) -> bool:
    return bool(disturbed_phases(record) or wide_phases(record))


def covered(first: CellRecord, second: CellRecord, shift: float = 1.0) -> bool:
    """Whether run 2's p50 (÷ `shift`, the machine's move between the runs) lies in run 1's interval."""
    interval = first.metrics.latency.p50_ci
    return interval is not None and interval[0] <= second.metrics.latency.p50 / shift <= interval[1]


def machine_line(pairs: list[tuple[CellRecord, CellRecord]]) -> str:
    """How the machine's speed moved between the runs (the median of the cells' p50 ratios, run 2 ÷ run 1),
    and how many of run 1's intervals hold run 2's p50 with that move taken out (what one run can know)."""
    ratios = [two.metrics.latency.p50 / one.metrics.latency.p50 for one, two in pairs]
    shift = statistics.median(ratios) if ratios else 1.0
    same = sum((r > 1) == (shift > 1) for r in ratios if r != 1)
    held = sum(covered(one, two, shift) for one, two in pairs)
    return (f"the machine between the runs: p50s moved by a median of {shift - 1:+.1%} ({same} of "
            f"{len(ratios)} cells the same way); with that move taken out, run 1's intervals hold {held} of "
            f"{len(pairs)}")


def rounds_s(records: list[CellRecord]) -> float:
    """Seconds spent in rounds: each model's once."""
    by_model = {r.cell.model: (r.metrics.setup.timing_window or {}).get("rounds_s", 0.0) for r in records}
    return sum(by_model.values())


def table(first: list[CellRecord], second: list[CellRecord]) -> list[str]:
    """One line per cell of both runs, then the summary line."""
    again = {r.cell.key: r for r in second}
    lines, moves, inside, flagged = [], [], [], 0
    pairs = [(one, again[one.cell.key]) for one in sorted(first, key=lambda r: r.cell.key)
             if one.cell.key in again]
    for one, two in pairs:
        s1, s2 = speedup(one), speedup(two)
        move = abs(s2 / s1 - 1) if s1 and s2 else None
        moves += [move] if move is not None else []
        inside.append(covered(one, two))
        flagged += marked(one) or marked(two)
        lines.append(f"{one.cell.label:<38} p50 {one.metrics.latency.p50:8.4f} "
                     f"{two.metrics.latency.p50:8.4f} ms"
                     f"  speed-up {_x(s1)} {_x(s2)}  diff {'—' if move is None else f'{move:6.1%}'}"
                     f"  {'in' if inside[-1] else 'OUT'}{'  ~' if marked(one) or marked(two) else ''}")
    median = statistics.median(moves) if moves else float("nan")
    lines.append(machine_line(pairs))
    lines.append(f"speed-up difference median {median:.1%}, max {max(moves, default=float('nan')):.1%}; "
                 f"p50 CI coverage {sum(inside) / max(len(inside), 1):.0%}; "
                 f"flagged {flagged} of {len(inside)}; timing {rounds_s(first) + rounds_s(second):.0f} s")
    return lines


def answers(workdir: Path, matrix: Path) -> list[str]:
    """Per model and target, both runs' recommended cells and verdicts; then `answers same N of M`."""
    stored = [load_judged(workdir / f"{label}.sqlite", judging=Judging(matrix)) for label in ("run1", "run2")]
    judged = [{m.name: m for m in found.report.models} for found in stored]
    lines, same, total = [], 0, 0
    for name in sorted(set(judged[0]) & set(judged[1])):
        one, two = judged[0][name], judged[1][name]
        for first, second in zip(one.recommendations, two.recommendations):
            verdicts = [_verdicts(model) for model in (one, two)]
            agree = _best(first) == _best(second) and verdicts[0] == verdicts[1]
            same, total = same + agree, total + 1
            changed = sorted(k for k in verdicts[0] if verdicts[0][k] != verdicts[1].get(k))
            lines.append(f"{name} on {first.target}: recommended {_said(first)} | {_said(second)}; verdicts "
                         + ("the same" if not changed else f"differ for {', '.join(changed)}"))
    return lines + [f"answers same {same} of {total}"]


def _verdicts(model: ModelSummary) -> dict[str, str]:
    return {row.record.cell.key: row.verdict.status for row in model.rows if row.verdict is not None}


def _best(found) -> str | None:
    return found.best.cell.key if found.best is not None else None


def _said(found) -> str:
    told = {True: "distinguishable", False: "a tie", None: "no runner-up"}[found.distinguishable]
    return f"{found.best.cell.label if found.best else 'none'} ({told})"


def _x(value: float | None) -> str:
    return "    —" if value is None else f"{value:5.2f}×"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--matrix", type=Path, help="a matrix file (default: the built-in one above)")
    parser.add_argument("--hog", action="store_true", help="a CPU-bound process on the other core in run 2")
    parser.add_argument("--workdir", type=Path)
    args = parser.parse_args()
    workdir = args.workdir or Path(tempfile.mkdtemp(prefix="bench-matrix-repro-"))
    workdir.mkdir(parents=True, exist_ok=True)
    matrix = args.matrix.resolve() if args.matrix else workdir / "matrix.yaml"
    if not args.matrix:
        matrix.write_text(MATRIX)
    print(f"workdir {workdir}: run 1 (preparing data and models first)...", flush=True)
    first = run(workdir, matrix, "run1")
    print("run 2" + (" under a CPU-bound process on the other core" if args.hog else "") + "...", flush=True)
    competitor = hog() if args.hog else None
    try:
        second = run(workdir, matrix, "run2")
    finally:
        if competitor is not None:
            competitor.kill()
            competitor.wait()
    print("\n".join(table(first, second) + answers(workdir, matrix)))


if __name__ == "__main__":
    main()

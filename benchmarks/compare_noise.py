"""How often `compare` calls unchanged cells changed: the same seven cells (the PilotNet matrix below)
measured REPEATS times with `run --force` into one store, then every consecutive pair of runs
compared at the default thresholds. Nothing changed between the runs, so every "worse" or "better" is a false
alarm; the table gives, per metric, how often one occurred and how large the run-to-run changes were (the
quantiles the default thresholds in docs/results.md are chosen from).

    .venv/bin/python benchmarks/compare_noise.py [--repeats 6] [--workdir DIR] [--compare-only]

--compare-only compares the runs already in WORKDIR again (after a change to `compare`).
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

from bench_matrix.report.analysis.compare import DEFAULT_THRESHOLDS, METRICS

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
settings: {threads: 1, warmup_iterations: 20, warmup_s: 0.5}
"""


def bench_matrix(workdir: Path, *args: str) -> subprocess.CompletedProcess:
    command = [sys.executable, "-m", "bench_matrix.cli", "--workspace", str(workdir / "ws"), *args]
    return subprocess.run(command, cwd=workdir, capture_output=True, text=True)


def measure(workdir: Path, repeats: int) -> None:
    (workdir / "m.yaml").write_text(MATRIX)
    for number in range(1, repeats + 1):
        done = bench_matrix(workdir, "run", "m.yaml", "--force", "--label", f"repeat-{number}")
        if done.returncode != 0:
            sys.exit(f"run {number} failed:\n{done.stdout}\n{done.stderr}")
        print(f"run {number}/{repeats} done", flush=True)


def comparisons(workdir: Path, repeats: int) -> list[dict]:
    found = []
    for number in range(2, repeats + 1):
        out = bench_matrix(workdir, "compare", f"repeat-{number - 1}", f"repeat-{number}", "--format", "json")
        if out.returncode not in (0, 1):
            sys.exit(f"compare failed:\n{out.stderr}")
        found.append(json.loads(out.stdout))
    return found


def summary(results: list[dict]) -> list[str]:
    """Per metric: pairs compared, false alarms, and quantiles of |relative change| between unchanged runs."""
    lines = ["| metric | default threshold | cell pairs | worse | better | not comparable (interference) | "
             "|change| p50 | p90 | max |", "|---|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for name in METRICS:
        every = [c["metrics"][name] for result in results for c in result["cells"] if name in c.get("metrics", {})]
        changes = [c for c in every if c["verdict"] != "not comparable"]
        noisy = sum("interference" in (c.get("why") or "") for c in every)
        sizes = np.abs([c["change"] for c in changes if c.get("change") is not None]) * 100
        verdicts = [c["verdict"] for c in changes]
        quantiles = [f"{q:.1f} %" for q in np.percentile(sizes, [50, 90, 100])] if len(sizes) else ["—"] * 3
        limit = DEFAULT_THRESHOLDS.get(name)
        lines.append(f"| {name} | {f'{limit:.0%}' if limit is not None else 'by metric'} | {len(every)} | "
                     f"{verdicts.count('worse')} | {verdicts.count('better')} | {noisy} | "
                     f"{' | '.join(quantiles)} |")
    return lines


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=6)
    parser.add_argument("--workdir", type=Path, help="keep the workspace and store here (default: temp)")
    parser.add_argument("--compare-only", action="store_true", help="compare WORKDIR's runs, measure nothing")
    args = parser.parse_args()
    workdir = args.workdir or Path(tempfile.mkdtemp(prefix="compare-noise-"))
    workdir.mkdir(parents=True, exist_ok=True)
    if not args.compare_only:
        measure(workdir, args.repeats)
    results = comparisons(workdir, args.repeats)
    (workdir / "comparisons.json").write_text(json.dumps(results, indent=1))
    gated = sum(bool(r.get("regressions")) for r in results)
    print("\n".join(summary(results)))
    print(f"\n{gated} of {len(results)} comparisons of unchanged runs would have failed a CI gate "
          f"(exit 1); details in {workdir / 'comparisons.json'}")


if __name__ == "__main__":
    main()

"""The reference study's published offline figures beside our measurement of matrices/pilotnet-study.yaml.

Reads the stored results of a run of that matrix (nothing is re-measured) and prints a Markdown page. The study's
figures are quoted from its posts (../shared/seeds, JdeRobot GSoC 2022); its "MB" are MiB (64.917 MB is the fp32
.tflite of 17,016,206 parameters). Sizes compare directly (same architectures); MSE does not (different data and
models), so each side's MSE is shown as its change relative to that side's own baseline.

    .venv/bin/python benchmarks/study_comparison.py --workspace .bench-matrix/study > reports/pilotnet-study/vs-study.md
"""

from __future__ import annotations

import argparse
from pathlib import Path

from bench_matrix.store import CellRecord, ResultStore

MIB = 1024 * 1024
# (label, our model, backend, strategy, precision, study size MiB, study MSE); None where the study gave none.
TF_SOURCE = "study blog, week 'Quantization Aware Training correction and benchmarking' (seed 002)"
TORCH_SOURCE = "study blog, PyTorch quantisation results (seed 004)"
TF_ROWS = [
    ("baseline (fp32 .tflite)", "tflite", "none", "fp32", 64.9173469543457, 0.04108056542969754),
    ("dynamic-range quantisation", "tflite", "ptq_dynamic", "int8", 16.242530822753906, 0.04098070281274293),
    ("float16 quantisation", "tflite", "none", "fp16", 32.464256286621094, 0.041072421023905605),
    ("weight pruning", "tflite", "prune", "fp32", 64.9173469543457, 0.04257505210072217),
    ("weight pruning + quantisation", "tflite", "prune_quant", "int8", 16.242530822753906, 0.042606822364652304),
    ("integer only (int8 in/out)", "tflite", "ptq_full_int8", "int8", 16.244918823242188, 28157.721509850544),
    ("integer, float fallback", "tflite", "ptq_static", "int8", 16.244888305664062, 0.04507085706016211),
    ("QAT", "tflite", "qat", "int8", 16.250564575195312, 0.042138221871067326),
    ("CQAT", "tflite", "cqat", "int8", 16.250564575195312, 0.0393811650675438),
    ("PQAT", "tflite", "pqat", "int8", 16.250564575195312, 0.043669467093106665),
    ("PCQAT", "tflite", "pcqat", "int8", 16.250564575195312, 0.039242053481006144),
    ("TF-TRT FP32", "tftrt", "none", "fp32", 260.0, 0.04103255125749467),
    ("TF-TRT FP16", "tftrt", "none", "fp16", 260.0, 0.04103255125749467),
]
TORCH_ROWS = [
    ("baseline (TorchScript)", "torchscript", "none", "fp32", 6.118725776672363, 0.08102315874947678),
    ("dynamic quantisation", "torchscript", "ptq_dynamic", "int8", 1.9464960098266602, 0.0807250236781935),
    ("static quantisation", "torchscript", "ptq_static", "int8", 1.6051549911499023, 0.08005780008222375),
    ("QAT", "torchscript", "qat", "int8", 1.6069040298461914, 0.06957647389277727),
    ("local L1 pruning", "torchscript", "prune_local", "fp32", None, None),
    ("global L1 pruning", "torchscript", "prune_global", "fp32", None, None),
    ("local pruning + quantisation", "torchscript", "prune_local_quant", "int8", None, None),
]


def _pct(value: float | None, base: float | None) -> str:
    if value is None or not base:
        return "—"
    change = (value / base - 1) * 100
    return f"{change:+.1f} %" if abs(change) < 1e4 else f"×{value / base:,.0f}"


def _num(value: float | None, fmt: str) -> str:
    return "—" if value is None else format(value, fmt)


def _table(title: str, source: str, model: str, rows: list, found: dict[tuple, CellRecord]) -> list[str]:
    base_cell = (model, *rows[0][1:4])
    ours_base = found.get(base_cell)
    base_mse = ours_base.metrics.task.mse if ours_base and ours_base.status == "ok" else None
    study_base = rows[0][5]
    out = [f"## {title}", "", f"Study figures: {source}. Ours: `{model}`; our baseline row is the cell "
           f"`{'/'.join(base_cell[1:])}/cpu`.", "",
           "| method | our cell | study MiB | our MiB | our gzip MiB | sparsity | study ΔMSE | our ΔMSE | our MSE |",
           "|---|---|---|---|---|---|---|---|---|"]
    for label, backend, strategy, precision, size, mse in rows:
        record = found.get((model, backend, strategy, precision))
        cell = f"`{backend}/{strategy}/{precision}`"
        if record is None or record.status != "ok":
            why = record.reason.split(";")[0] if record is not None and record.reason else "not in the matrix"
            out.append(f"| {label} | {cell} | {_num(size, '.2f')} | not run: {why} | | | {_pct(mse, study_base)} | | |")
            continue
        m = record.metrics
        out.append(f"| {label} | {cell} | {_num(size, '.2f')} | {m.size.bytes / MIB:.2f} | "
                   f"{m.size.gzip_bytes / MIB:.2f} | {_num(m.figure('sparsity'), '.3f')} | {_pct(mse, study_base)} | "
                   f"{_pct(m.task.mse, base_mse)} | {_num(m.task.mse, '.6f')} |")
    return out + [""]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--workspace", type=Path, default=Path(".bench-matrix/study"))
    args = parser.parse_args()
    store = ResultStore(args.workspace / "results.sqlite")
    try:
        found = {(r.cell.model, r.cell.backend, r.cell.strategy, r.cell.precision): r for r in store.records()
                 if r.cell.target in ("cpu", "tensorrt")}
        infos = {name: store.facts(f"model:{name}").get("info", {}) for name in ("jderobot-tf", "jderobot-torch")}
    finally:
        store.close()
    lines = ["# PilotNet study: the reference study's offline figures beside ours", "",
             "Generated by `benchmarks/study_comparison.py` from the stored results of "
             "`bench-matrix --workspace .bench-matrix/study run matrices/pilotnet-study.yaml`; the full tables "
             "(latency, throughput, environment) are in [index.md](index.md).", "",
             "ΔMSE is each side's MSE relative to its own baseline: the study's models and data differ from ours "
             "(its TF baseline MSE is 0.0411, ours is measured on the built-in driving dataset), so only the "
             "direction and rough size of a change compare, and sizes compare directly.", ""]
    for name, info in infos.items():
        if info:
            lines.append(f"- `{name}`: {info.get('params', 0):,} parameters, baseline test MSE "
                         f"{info.get('test_mse', float('nan')):.6f} (mean predictor {info.get('mean_predictor_mse', 0):.5f}).")
    lines.append("")
    lines += _table("TensorFlow variant: TFLite and TF-TRT", TF_SOURCE, "jderobot-tf", TF_ROWS, found)
    lines += _table("PyTorch variant: TorchScript", TORCH_SOURCE, "jderobot-torch", TORCH_ROWS, found)
    lines += ["The study gave no sizes or MSE figures for its PyTorch pruning rows; its summary says only that "
              "pruning + quantisation improved MSE by 0.011 over the baseline (seed 000).", ""]
    print("\n".join(lines))


if __name__ == "__main__":
    main()

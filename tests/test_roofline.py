"""The roofline (docs/metrics.md §17): FLOPs and bytes of a small Conv + Gemm ONNX model against a hand count
(and its int8 graph's FLOPs the same), the machine's peak by an injected clock, the bound's arithmetic, and
the report's section: the short terminal form, the plots, and nothing where no cell was profiled."""

from __future__ import annotations

import io
import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from rich.console import Console

from bench_matrix.cell import Cell
from bench_matrix.measure.peak import best_of, best_rate, measure, ort_kernels
from bench_matrix.measure.work import onnx_work
from bench_matrix.report.analysis.roofline import best_peaks, model_work, roofline
from bench_matrix.report.analysis.summary import Row, summarize
from bench_matrix.scenarios.profile.plots import profile_plots
from bench_matrix.report.render.terminal import print_block
from bench_matrix.scenarios.profile.report import blocks
from bench_matrix.store import CellRecord
from bench_matrix.tensors import TensorSpec
from tiny_models import conv_gemm

X = TensorSpec("X", (3, 16, 16))
# Conv 3→8, 3×3, padded: 8×16×16 outputs × 27 multiply-adds; Gemm 2048→4: 4 outputs × 2048 of them
CONV_FLOPS, GEMM_FLOPS = 2 * 8 * 16 * 16 * 27, 2 * 4 * 2048
# weights: conv 8×3×3×3 + 8, gemm 2048×4 + 4 (fp32), the reshape's shape 2 × int64
WEIGHT_BYTES = 4 * (8 * 27 + 8 + 2048 * 4 + 4) + 2 * 8
# activations, each once: X (3×16×16), the conv's, the relu's and the reshape's outputs (2048 each), Y (4)
ACTIVATION_BYTES = 4 * (3 * 16 * 16 + 3 * 2048 + 4)


def test_flops_and_bytes_of_a_conv_gemm_model_equal_a_hand_count() -> None:
    work = onnx_work(conv_gemm(), [X])
    assert work.reason is None
    assert work.by_op == {"Conv": CONV_FLOPS, "Gemm": GEMM_FLOPS} and work.flops == CONV_FLOPS + GEMM_FLOPS
    assert (work.weight_bytes, work.activation_bytes) == (WEIGHT_BYTES, ACTIVATION_BYTES)
    assert work.to_json()["bytes"] == WEIGHT_BYTES + ACTIVATION_BYTES


def test_its_dynamic_int8_graph_does_the_same_multiply_adds(tmp_path: Path) -> None:
    import onnx
    from onnxruntime.quantization import quantize_dynamic

    onnx.save(conv_gemm(), str(tmp_path / "fp32.onnx"))
    quantize_dynamic(tmp_path / "fp32.onnx", tmp_path / "int8.onnx")
    quantised = onnx.load(str(tmp_path / "int8.onnx"))
    assert {"ConvInteger", "MatMulInteger"} <= {node.op_type for node in quantised.graph.node}
    work = onnx_work(quantised, [X])
    assert work.flops == CONV_FLOPS + GEMM_FLOPS and work.weight_bytes < WEIGHT_BYTES, work


def test_a_free_axis_is_a_reason_never_a_guess() -> None:
    work = onnx_work(conv_gemm(), [TensorSpec("X", (3, None, 16))])
    assert work.reason == "input X has a free axis: its length at inference is not known"
    assert work.to_json() == {"reason": work.reason}


class Clock:
    """A kernel's clock: each call moves it on by the next of its durations."""

    def __init__(self, durations: list[float]):
        self.now, self.durations = 0.0, durations

    def call(self) -> None:
        self.now += self.durations.pop(0) if self.durations else 1.0


def test_the_peak_is_the_fastest_call_of_each_kernel_by_an_injected_clock() -> None:
    gemm = Clock([9.0, 0.5, 0.25, 0.4])  # the untimed first call, then 3 timed: the fastest is 0.25 s
    stream = Clock([1.0, 2.0, 2.0, 4.0])
    kernels = {"fp32": (gemm.call, 1e9), "stream": (stream.call, 6e9), "bf16": ("no bf16 here", 0.0)}
    peak = measure(2, kernels, seconds=0.0, clock=lambda: gemm.now + stream.now)
    assert peak.flops == {"fp32": 4e9} and peak.bandwidth == 3e9
    assert peak.fields() == {"machine_threads": 2, "machine_flops": {"fp32": 4_000_000_000},
                             "machine_bandwidth": 3_000_000_000, "machine_reasons": {"bf16": "no bf16 here"}}


def test_a_cpu_without_int8_or_bf16_instructions_gets_reasons_not_peaks() -> None:
    kernels = ort_kernels(1, frozenset({"avx2"}))
    assert callable(kernels["fp32"][0]) and callable(kernels["stream"][0])
    assert kernels["int8"][0] == "the CPU has no int8 dot-product instructions (VNNI, AMX, dotprod)"
    assert kernels["bf16"][0] == "the CPU has no bf16 instructions (AVX-512 BF16, AMX, ARM bf16)"


def test_two_peaks_of_a_machine_keep_each_best_and_are_disturbed_only_where_both_were() -> None:
    held = {"machine_flops": {"fp32": 5e10, "int8": 4e11}, "machine_bandwidth": 2e10, "machine_host": "h",
            "machine_reasons": {"bf16": "none here"}, "machine_disturbed": "busy", "machine_measurements": 2}
    found = {"machine_flops": {"fp32": 9e10, "int8": 3e11, "bf16": 1e11}, "machine_bandwidth": 1e10,
             "machine_reasons": {}, "machine_disturbed": "busy too"}
    best = best_of(held, found)
    assert best["machine_flops"] == {"fp32": 9e10, "int8": 4e11, "bf16": 1e11}
    assert best["machine_bandwidth"] == 2e10 and best["machine_reasons"] == {}
    assert best["machine_disturbed"] == "busy too" and best["machine_measurements"] == 3
    assert best_of(held, {**found, "machine_disturbed": None})["machine_disturbed"] is None


def test_a_clock_that_does_not_move_gives_no_rate() -> None:
    with pytest.raises(ValueError, match="no rate"):
        best_rate(lambda: None, 1e9, 0.0, lambda: 0.0)


def record(precision: str, p50: float | None = 1.0, profiled: bool = True, strategy: str | None = None,
           timed: bool = True, **others: Any) -> CellRecord:
    """An ok cell of model m; profiled: with a conv/gemm profile, the work and a peak."""
    strategy = strategy or ("none" if precision == "fp32" else "ptq_dynamic")
    cell = Cell("m", "onnx", "onnxruntime", strategy, precision, "cpu")
    ops = [{"name": "c", "op_type": "Conv", "kind": "conv", "precision": "fp32", "ms": 0.6},
           {"name": "g", "op_type": "MatMulInteger", "kind": "matmul", "precision": precision, "ms": 0.3},
           {"name": "q", "op_type": "DynamicQuantizeLinear", "kind": "quant", "precision": precision,
            "ms": 0.1}]
    machine = {"work_flops": 10**8, "work_bytes": 10**6, "work_weight_bytes": 8 * 10**5,
               "machine_threads": 1, "machine_flops": {"fp32": 2e11, "int8": 8e11}, "machine_bandwidth": 2e10,
               "machine_host": "h", "machine_cpu": "a CPU",
               "machine_measured_at": "2026-12-07T05:00:00+00:00"}
    profile = {"profile_calls": 5, "profile_ms": 1.0, "profile_operators": ops, **machine} if profiled else {}
    return CellRecord(cell=cell, status="ok", env={"host": "h"},
                      metrics={**({"latency_ms": {"p50": p50, "p99": 2.0}} if timed else {}), **profile,
                               **others})


def row(found: CellRecord) -> Row:
    return Row(found, False, None, None, None)


def test_the_roofline_bound_is_the_lower_of_the_ceiling_and_intensity_times_bandwidth() -> None:
    fp32 = roofline(row(record("fp32", p50=2.0)))  # 1e8 FLOP in 2 ms: 5e10 FLOP/s; 100 FLOP/byte
    assert fp32 is not None and (fp32.achieved, fp32.intensity) == (5e10, 100.0)
    assert fp32.bound == 2e11 and fp32.share == 0.25 and not fp32.memory_bound and fp32.ridge == 10.0
    starved = roofline(row(record("int8", work_bytes=10**7)))  # 10 FLOP/byte × 2e10 B/s = 2e11 < 8e11
    assert starved is not None and starved.memory_bound and starved.bound == 2e11 and starved.share == 0.5
    no_int8 = roofline(row(record("int8", machine_flops={"fp32": 2e11})))
    assert no_int8 is not None and no_int8.ceiling_of == "fp32" and no_int8.bound == 2e11
    uncounted = record("fp32", p50=2.0, work_flops=None, work_bytes=None, work_reason="pytorch: counts none")
    assert roofline(row(uncounted)) is None  # its model's work is its own cell's or another cell's
    assert roofline(row(uncounted), [row(record("int8"))]) == fp32
    on_gpu = record("fp32")
    on_gpu.cell = Cell("m", "onnx", "onnxruntime", "none", "fp32", "cuda")
    assert roofline(row(on_gpu)) is None
    assert model_work([row(record("fp32", work_bytes=0))]) == {}  # never a division by zero
    for broken in (record("fp32", p50=None), record("fp32", p50=math.nan), record("fp32", work_bytes=0),
                   record("fp32", machine_flops={}), record("fp32", profiled=False),
                   record("fp32", timed=False)):
        assert roofline(row(broken)) is None


def test_a_kept_peak_measured_again_counts_each_measurement_once() -> None:
    first = record("fp32", machine_flops={"fp32": 1e11}, machine_disturbed="busy")
    grown = record("fp32", strategy="x", machine_flops={"fp32": 1.5e11}, machine_measurements=2,
                   machine_disturbed="busy")  # the first one measured again: its line, grown
    other = record("fp32", strategy="y", machine_flops={"fp32": 1.2e11, "int8": 4e11},
                   machine_measured_at="later")
    peak = best_peaks([row(first), row(grown), row(other)])[("h", "a CPU", 1)]
    assert peak["machine_measurements"] == 3 and peak["machine_flops"] == {"fp32": 1.5e11, "int8": 4e11}
    assert peak["machine_disturbed"] is None  # the other line was quiet


def test_the_section_shows_the_short_form_and_the_plots_and_nothing_without_a_profile(tmp_path: Path) -> None:
    infos = {"m": {"framework": "onnx", "baseline_key": "m/onnxruntime/none/fp32/cpu", "task": "regression"}}
    slower = record("int8", p50=0.5, machine_flops={"fp32": 1e11, "int8": 8e11}, machine_bandwidth=1e10,
                    machine_disturbed="busy", machine_measured_at="later")  # lower: held to the best
    model = summarize([record("fp32"), record("fp32", strategy="other"), slower], infos, {}).models[0]
    console = Console(file=io.StringIO(), width=250)
    print_block(model, *blocks(model), console)
    text = console.file.getvalue()
    assert "Top kinds" in text and "conv fp32 60 %, matmul int8 30 %, quant int8 10 %" in text
    assert "50.0 (fp32)" in text and "25.0 (int8)" in text  # 1e11 of 2e11; 2e11 of 8e11
    assert "float in int8 %" in text and "conv fp32 %" not in text  # the short form: no column per kind
    assert "Work of one inference (its fp32 ONNX graph): 100 MFLOP, 1 MB" in text
    assert "the best of 2 measurements: fp32 200 GFLOP/s, int8 800 GOP/s; stream 20 GB/s" in text
    assert "disturbed" not in text  # one of the two was quiet
    plots = profile_plots(model, tmp_path / "plots")
    assert [p.kind for p in plots] == ["profile", "roofline"] and all(p.path.stat().st_size for p in plots)
    bare = summarize([record("fp32", profiled=False)], infos, {}).models[0]
    console = Console(file=io.StringIO(), width=250)
    assert blocks(bare) == []
    assert console.file.getvalue() == "" and profile_plots(bare, tmp_path / "bare") == []

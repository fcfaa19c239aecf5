"""Closed-loop margins in the records' consumers, on records made by hand: the verdict's margin requirements,
the report's margins table (beside the baseline, with the ratio), how far apart the cells are, the plot."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from bench_matrix.cell import Cell
from bench_matrix.matrix.requirements import Requirements
from bench_matrix.report.analysis.summary import summarize
from bench_matrix.report.render.markdown import block_lines
from bench_matrix.scenarios.closed_loop.margin_report import blocks, margin_plots
from bench_matrix.store import CellRecord
from bench_matrix.verdict import FAIL, PASS, judge

BASE = Cell("m", "pytorch", "pytorch", "none", "fp32", "cpu")
SCRIPTED = Cell("m", "pytorch", "torchscript", "none", "fp32", "cpu")
INT8 = Cell("m", "pytorch", "onnxruntime", "ptq_static", "int8", "cpu")


def answer(outcome: str, value: float | None, resolution: float = 10.0) -> dict[str, Any]:
    failed_at = {"passes_at_limit": None, "fails_at_start": 0.0}.get(outcome, (value or 0.0) + resolution)
    return {"outcome": outcome, "value": value, "failed_at": failed_at, "resolution": resolution,
            "probes": [], "start": 0.0, "limit": 500.0, "laps": 7, "wall_s": 12.0}


def record(cell: Cell, **margins: dict[str, Any]) -> CellRecord:
    """A driven cell whose margins on the hairpin circuit are `margins`, each kind's answer."""
    return CellRecord(cell=cell, status="ok", env={"host": "h"},
                      metrics={"closed_loop": {"hairpin": {"lock_step": {"completed_pct": 100.0}}},
                               "closed_loop_margins": {"hairpin": margins}})


def status(requirements: dict[str, Any], cell: CellRecord) -> tuple[str, list[str]]:
    verdict = judge(cell.metrics, Requirements.from_data(requirements), "regression", None)
    return verdict.status, [c.text for c in verdict.failed]


def test_the_verdict_bounds_each_margin() -> None:
    cell = record(INT8, latency=answer("found", 120.0), speed=answer("passes_at_limit", 2.5, 0.05),
                  perception=answer("fails_at_start", None, 0.05))
    assert status({"closed_loop": {"latency_margin_ms": 100, "speed_margin": 2.5}}, cell)[0] == PASS
    assert status({"closed_loop": {"latency_margin_ms": 150}}, cell) == (
        FAIL, ["closed_loop.latency_margin_ms 120 < 150 (20 % under)"])
    assert status({"closed_loop": {"latency_margin_ms": {"min": 150}}}, cell) == (
        FAIL, ["closed_loop.latency_margin_ms 120 < 150 (20 % under)"])  # the bound named
    assert status({"closed_loop": {"perception_margin": 0}}, cell) == (
        FAIL, ["closed_loop.perception_margin not measured"])  # the unchanged lap already failed


def test_the_margins_table_sets_each_cell_beside_the_baseline(tmp_path: Path) -> None:
    records = [record(BASE, latency=answer("found", 200.0), speed=answer("found", 1.6, 0.05)),
               record(INT8, latency=answer("found", 150.0), speed=answer("passes_at_limit", 2.5, 0.05))]
    (model,) = summarize(records, {"m": {"baseline_key": BASE.key}}, {}).models
    page = "\n".join(line for block in blocks(model) for line in block_lines(block))
    assert "| Method | Circuit | Latency margin ms | × baseline | Speed margin × | × baseline |" in page
    assert "| pytorch none fp32 (baseline) | hairpin | 200–210 | 1.00 | 1.6–1.65 | 1.00 | 14 | 24 |" in page
    assert "| onnxruntime ptq_static int8 | hairpin | 150–160 | 0.75 | ≥ 2.5 | ≥ 1.56 | 14 | 24 |" in page
    assert ("- hairpin, latency: from 150 (onnxruntime ptq_static int8) to 200 (pytorch none fp32), "
            "resolution 10") in page
    (plot,) = margin_plots(model, tmp_path)
    assert plot.path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_cells_the_search_cannot_tell_apart_are_said_to_be_alike() -> None:
    records = [record(BASE, latency=answer("found", 200.0)), record(INT8, latency=answer("found", 200.0))]
    (model,) = summarize(records, {"m": {"baseline_key": BASE.key}}, {}).models
    page = "\n".join(line for block in blocks(model) for line in block_lines(block))
    alike = "- hairpin, latency: every cell's margin is 200: alike to within the search's resolution, 10"
    assert alike in page


def test_a_cell_that_drove_without_a_margin_search_is_named() -> None:
    driven = CellRecord(cell=SCRIPTED, status="ok", env={"host": "h"},
                        metrics={"closed_loop": {"hairpin": {"lock_step": {"completed_pct": 100.0}}}})
    records = [record(BASE, latency=answer("found", 200.0)), driven]
    (model,) = summarize(records, {"m": {"baseline_key": BASE.key}}, {}).models
    page = "\n".join(line for block in blocks(model) for line in block_lines(block))
    assert "| torchscript none fp32 |" not in page
    assert "- hairpin, latency:" not in page  # one cell searched: no spread to state
    assert "- Not searched: torchscript none fp32 (they drove their laps;" in page
    (model,) = summarize(records[:1], {"m": {"baseline_key": BASE.key}}, {}).models
    assert "Not searched" not in "\n".join(line for block in blocks(model) for line in block_lines(block))


def test_the_spread_names_every_cell_at_each_end_or_counts_them() -> None:
    cells = [Cell("m", "pytorch", backend, "none", "fp32", "cpu")
             for backend in ("torchscript", "torch_compile", "onnxruntime")]
    records = [record(BASE, latency=answer("found", 200.0)), record(INT8, latency=answer("found", 150.0)),
               *(record(cell, latency=answer("found", 200.0)) for cell in cells)]
    (model,) = summarize(records, {"m": {"baseline_key": BASE.key}}, {}).models
    page = "\n".join(line for block in blocks(model) for line in block_lines(block))
    assert "- hairpin, latency: from 150 (onnxruntime ptq_static int8) to 200 (4 cells), resolution 10" \
        in page
    (model,) = summarize(records[:3], {"m": {"baseline_key": BASE.key}}, {}).models
    page = "\n".join(line for block in blocks(model) for line in block_lines(block))
    assert "to 200 (pytorch none fp32 and torchscript none fp32), resolution 10" in page

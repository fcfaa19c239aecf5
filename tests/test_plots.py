"""Report plots from hand-made records: the Pareto set, non-overlapping text for 40 cells, the files written
and returned, their names, and what is left out when data is missing."""

from __future__ import annotations

import itertools
import subprocess
import sys
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from bench_matrix.cell import Cell
from bench_matrix.report.analysis.pareto import pareto_optimal, points
from bench_matrix.report.analysis.summary import ModelSummary, summarize
from bench_matrix.report.render.pareto_layout import Box, place_labels, reference_sizes
from bench_matrix.report.render.plots import file_stem, latency_figure, model_plots, pareto_figure
from bench_matrix.report.render.sections import section_plots
from bench_matrix.store import CellRecord

MIB = 2**20
BACKENDS = ("pytorch", "torchscript", "onnxruntime", "tensorflow", "tflite")
STRATEGIES = ("none", "ptq_dynamic", "ptq_static", "prune_local")
PRECISIONS = ("fp32", "fp16", "int8")


def _metrics(p50: float | None, accuracy: float | None, size_mib: float = 4.0, key: str = "mse"
             ) -> dict[str, Any]:
    metrics: dict[str, Any] = {"size_bytes": int(size_mib * MIB)}
    if p50 is not None:
        metrics["latency_ms"] = {"p50": p50, "p90": p50 * 1.2, "p99": p50 * 1.5,
                                 "p50_ci": [p50 * 0.98, p50 * 1.03]}
    if accuracy is not None:
        metrics[key] = accuracy
    return metrics


def _summary(name: str, cells: list[tuple[Cell, dict[str, Any]]], task: str = "regression",
             extra: list[CellRecord] = ()) -> ModelSummary:
    records = [CellRecord(cell=cell, status="ok", metrics=metrics, id=number)
               for number, (cell, metrics) in enumerate(cells, 1)] + list(extra)  # ids: samples' keys
    info = {"task": task, "baseline_key": records[0].cell.key if records else ""}
    return summarize(records, {name: info}, {}).models[0]


def _cell(model: str, backend: str, strategy: str = "none", precision: str = "fp32", target: str = "cpu"
          ) -> Cell:
    return Cell(model, "pytorch", backend, strategy, precision, target)


def forty(name: str = "pilot net/v2", task: str = "regression", count: int = 40
          ) -> tuple[ModelSummary, dict[int, np.ndarray]]:
    """`count` cells crowded as real matrices are: a few latency clusters, repeated accuracies, four sizes."""
    rng = np.random.default_rng(7)
    combos = list(itertools.product(BACKENDS, STRATEGIES, PRECISIONS, ("cpu", "cuda")))
    cells, samples = [], {}
    for k in range(count):
        backend, strategy, precision, target = combos[(k * 7) % len(combos)]
        cell = _cell(name, backend, strategy, precision, target)
        p50 = float(rng.choice([0.8, 1.0, 1.1, 3.0, 9.0]) * rng.uniform(0.97, 1.03))
        error = float(rng.choice([0.0123, 0.0123, 0.0125, 0.013, 0.02]) / (p50 ** 0.1))
        accuracy = 1 - 10 * error if task == "classification" else error
        key = "top1" if task == "classification" else "mse"
        cells.append((cell, _metrics(p50, accuracy, float(rng.choice([1, 2.5, 4, 16])), key)))
        samples[k + 1] = (p50 * rng.lognormal(0, 0.1, 300)).astype(np.float32)
    return _summary(name, cells, task), samples


# ---- the Pareto set --------------------------------------------------------------------------------------

def test_pareto_set_lower_is_better() -> None:
    pairs = [(1.0, 0.5), (2.0, 0.3), (3.0, 0.1), (2.5, 0.4), (1.5, 0.6), (4.0, 0.1)]
    # (2.5, 0.4) is slower and worse than (2.0, 0.3); (1.5, 0.6) slower and worse than (1.0, 0.5);
    # (4.0, 0.1) only ties (3.0, 0.1) on accuracy and is slower
    assert pareto_optimal(pairs, higher_is_better=False) == [True, True, True, False, False, False]


def test_pareto_set_higher_is_better() -> None:
    pairs = [(1.0, 0.5), (2.0, 0.3), (3.0, 0.9), (0.5, 0.2)]
    assert pareto_optimal(pairs, higher_is_better=True) == [True, False, True, True]


def test_pareto_ties_equal_cells_both_stay_and_one_sided_ties_are_dominated() -> None:
    pairs = [(1.0, 0.5), (1.0, 0.5), (1.0, 0.7), (2.0, 0.2), (3.0, 0.2)]
    # identical pairs do not dominate each other, but both lose to the equally fast, more accurate (1.0, 0.7)
    assert pareto_optimal(pairs, higher_is_better=True) == [False, False, True, False, False]
    assert pareto_optimal(pairs, higher_is_better=False) == [True, True, False, True, False]
    assert pareto_optimal([(1.0, 0.5)] * 3, higher_is_better=False) == [True] * 3
    assert pareto_optimal([], higher_is_better=False) == []


def test_points_leave_out_cells_without_latency_or_accuracy_and_number_the_rest() -> None:
    model = _summary("m", [(_cell("m", "pytorch"), _metrics(2.0, 0.01)),
                           (_cell("m", "onnxruntime"), _metrics(1.0, 0.02)),
                           (_cell("m", "tflite"), _metrics(None, 0.001)),
                           (_cell("m", "tensorflow"), _metrics(0.5, None)),
                           (_cell("m", "torchscript"), _metrics(0.7, float("nan")))])
    found, left_out = points(model)
    assert [(p.number, p.record.cell.backend, p.optimal) for p in found] == [
        (1, "pytorch", True), (2, "onnxruntime", True)]  # baseline first, then by p50
    assert found[1].ci == pytest.approx((0.98, 1.03)) and found[0].size_bytes == 4 * MIB
    assert sorted(r.cell.backend for r in left_out) == ["tensorflow", "tflite", "torchscript"]


def test_reference_sizes_are_round_and_span_the_sizes() -> None:
    assert [s / MIB for s in reference_sizes([1 * MIB, 16 * MIB])] == [1, 5, 10]
    assert [s / MIB for s in reference_sizes([0.3 * MIB, 0.45 * MIB])] == [0.45]  # no round size inside
    assert [s / MIB for s in reference_sizes([0.1 * MIB, 120 * MIB])] == [0.1, 5, 100]


def test_place_labels_keeps_labels_apart_inside_bounds() -> None:
    anchors = [(50.0, 50.0)] * 12  # one pile of identical points: the hardest case
    centres = place_labels(anchors, [5.0] * 12, [(12.0, 9.0)] * 12, Box(0, 0, 200, 120), gap=2.0)
    boxes = [Box(x - 6, y - 4.5, x + 6, y + 4.5) for x, y in centres]
    assert all(b.within(Box(0, 0, 200, 120)) for b in boxes)
    assert not any(a.overlaps(b) for a, b in itertools.combinations(boxes, 2))
    assert not any(b.hits_circle(50, 50, 5.0) for b in boxes)


# ---- drawing -----------------------------------------------------------------------------------------------

def _drawn_texts(figure: Any, monkeypatch: pytest.MonkeyPatch) -> list[tuple[str, Any]]:
    """Every non-empty text the figure actually draws, with its extent in pixels."""
    from matplotlib.text import Text

    drawn, draw = [], Text.draw

    def record(text: Text, renderer: Any) -> None:
        draw(text, renderer)
        if text.get_visible() and text.get_text().strip():
            drawn.append(text)

    monkeypatch.setattr(Text, "draw", record)
    figure.canvas.draw()
    renderer = figure.canvas.get_renderer()
    return [(t.get_text(), Text.get_window_extent(t, renderer)) for t in drawn]  # an annotation's: no arrow


def _overlapping(texts: list[tuple[str, Any]]) -> list[tuple[str, str]]:
    return [(a, b) for (a, box_a), (b, box_b) in itertools.combinations(texts, 2)
            if Box(*box_a.extents).overlaps(Box(*box_b.extents))]


@pytest.mark.parametrize("task", ["regression", "classification"])
def test_pareto_chart_of_40_cells_has_no_overlapping_text(task: str, monkeypatch: pytest.MonkeyPatch) -> None:
    model, _ = forty(task=task)
    found, _ = points(model)
    figure = pareto_figure(model, found)
    texts = _drawn_texts(figure, monkeypatch)
    numbers = {str(p.number) for p in found}
    assert numbers <= {text for text, _ in texts}  # every point numbered ...
    assert sum(text.startswith(f"{p.number}: ") for p in found for text, _ in texts) == 40  # ... and keyed
    assert _overlapping(texts) == []
    width, height = figure.canvas.get_width_height()
    assert all(0 <= b.x0 and b.x1 <= width and 0 <= b.y0 and b.y1 <= height for _, b in texts)  # nothing cut
    better = "higher is better" if task == "classification" else "lower is better"
    assert any(better in text for text, _ in texts) and any(" ms " in text for text, _ in texts)


def test_latency_chart_of_40_cells_has_no_overlapping_text(monkeypatch: pytest.MonkeyPatch) -> None:
    model, samples = forty()
    timed = sorted(((r.record, samples[r.record.id]) for r in model.rows),
                   key=lambda item: float(np.median(item[1])))
    texts = _drawn_texts(latency_figure(model, timed), monkeypatch)
    assert _overlapping(texts) == []
    assert sum(text == "n = 300" for text, _ in texts) == 40


def test_model_plots_writes_and_returns_each_kind(tmp_path: Path) -> None:
    model, samples = forty(count=12)
    del samples[model.rows[3].record.id]
    plots = model_plots(model, samples, tmp_path / "plots")
    assert [p.kind for p in plots] == ["pareto", "latency"]
    assert all(p.path.parent == tmp_path / "plots" and p.path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
               for p in plots)
    assert sorted(p.name for p in (tmp_path / "plots").iterdir()) == sorted(p.path.name for p in plots)
    missing = model.rows[3].record.cell.label
    assert f"Not shown (no raw samples stored): {missing}." in plots[1].alt
    optimal = [p.record.cell.label for p in points(model)[0] if p.optimal]
    assert optimal and f"Pareto-optimal: {', '.join(optimal)}." in plots[0].alt
    again = model_plots(model, samples, tmp_path / "again")
    assert [p.path.read_bytes() for p in again] == [p.path.read_bytes() for p in plots]  # deterministic


def test_trajectories_of_driven_cells_are_returned(tmp_path: Path) -> None:
    lap = {"trajectory": {"x": [0.0, 5.0, 9.0], "y": [0.0, 2.0, 1.0]}, "completed_pct": 40.0}
    circuit = {"reference": {"x": [0.0, 10.0, 10.0, 0.0], "y": [0.0, 0.0, 10.0, 10.0]}, "lane_width_m": 2.0}
    driven = {**_metrics(1.0, 0.01), "closed_loop": {"oval": {"lock_step": lap}},
              "closed_loop_circuits": {"oval": circuit}}
    model = _summary("m", [(_cell("m", "pytorch"), _metrics(2.0, 0.01)), (_cell("m", "onnxruntime"), driven)])
    plots = [*model_plots(model, {}, tmp_path), *section_plots(model, tmp_path)]
    assert [p.kind for p in plots] == ["pareto", "trajectory"]  # no samples: no latency distribution
    assert plots[1].path == tmp_path / "trajectory-m__onnxruntime__none__fp32__cpu.png"
    assert plots[1].path.is_file() and "onnxruntime none fp32" in plots[1].alt


def test_nothing_is_written_without_ok_cells(tmp_path: Path) -> None:
    skipped = CellRecord(cell=_cell("m", "tflite"), status="skipped", reason="no GPU")
    model = summarize([skipped], {"m": {"task": "regression"}}, {}).models[0]
    assert model_plots(model, {}, tmp_path / "plots") == []
    assert not (tmp_path / "plots").exists()


def test_one_cell_gets_a_distribution_but_no_pareto_chart(tmp_path: Path) -> None:
    cell = _cell("m", "pytorch")
    model = _summary("m", [(cell, _metrics(2.0, 0.01))])
    plots = model_plots(model, {1: np.full(50, 2.0, np.float32)}, tmp_path)
    assert [p.kind for p in plots] == ["latency"]


def test_equal_cells_without_size_or_interval_still_chart(tmp_path: Path) -> None:
    same = {"latency_ms": {"p50": 1.0}, "mse": 0.01}
    model = _summary("m", [(_cell("m", "pytorch"), same), (_cell("m", "onnxruntime"), same)])
    (plot,) = model_plots(model, {}, tmp_path)
    assert "Pareto-optimal: pytorch none fp32, onnxruntime none fp32." in plot.alt and plot.path.is_file()


def test_importing_the_plots_does_not_import_matplotlib() -> None:
    code = "import sys, bench_matrix.report.render.plots; print('matplotlib' in sys.modules)"
    found = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert found.stdout.strip() == "False"


@pytest.mark.parametrize("name", ["a b/c", "index", "../up", "a_b_c", "ünï cødé", "x" * 300, "$a$"])
def test_file_names_are_safe_and_unique_per_model(name: str, tmp_path: Path) -> None:
    first, second = _cell(name, "pytorch"), _cell(name, "onnxruntime")
    model = _summary(name, [(first, _metrics(2.0, 0.01)), (second, _metrics(1.0, 0.02))])
    plots = model_plots(model, {1: np.full(20, 2.0, np.float32)}, tmp_path)
    assert [p.kind for p in plots] == ["pareto", "latency"]
    assert {p.path.parent for p in plots} == {tmp_path}
    assert all(len(p.path.name) < 120 and p.path.name.isascii() and p.path.name.startswith(f"{p.kind}-")
               for p in plots)
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(p.path.name for p in plots)


def test_file_stems_differ_where_names_differ() -> None:
    names = ["a b/c", "a_b_c", "a b_c", "a_b/c", "Index", "index", ".", "..", "-", "a" * 300, "a" * 301]
    stems = [file_stem(n) for n in names]
    assert len(set(stems)) == len(names)
    assert file_stem("pilotnet-v2") == "pilotnet-v2"  # a safe name is kept as it is
    assert all(s[0].isalnum() and len(s) <= 100 for s in stems)

"""How far other runs on the same host put the same artifacts' p50s: the figures, the caption, the JSON."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from rich.console import Console

from bench_matrix.cell import Cell
from bench_matrix.report import load, write_report
from bench_matrix.report.analysis.reruns import Rerun, reruns
from bench_matrix.report.render.text import caption
from bench_matrix.store import CellRecord, ResultStore

CELLS = [Cell("tiny", "onnx", backend, "none", precision, "cpu")
         for backend, precision in (("onnxruntime", "fp32"), ("onnxruntime", "fp16"), ("openvino", "fp32"))]
P50 = {cell.key: p50 for cell, p50 in zip(CELLS, (0.50, 0.30, 0.20))}


def _record(cell: Cell, run: int, scale: float = 1.0, host: str = "vm", threads: int = 1,
            artifact: str | None = None, ci_half: float = 0.02) -> CellRecord:
    p50 = P50[cell.key] * scale
    latency = {"p50": p50, "p50_ci": [p50 / (1 + ci_half), p50 * (1 + ci_half)], "p50_ci_rel": 2 * ci_half}
    return CellRecord(cell=cell, status="ok", metrics={"latency_ms": latency, "threads": threads},
                      artifact_path=artifact or f"cache/artifacts/{cell.key}", env={"host": host},
                      run_id=run, matrix="m.yaml", fingerprint="f", started_at=f"2026-11-27T10:0{run}:00")


def test_each_other_run_of_the_artifacts_on_the_host_gives_its_move_and_what_the_intervals_held() -> None:
    shown = [_record(cell, run=3) for cell in CELLS]
    history = [*(_record(cell, 1, scale) for cell, scale in zip(CELLS, (1.06, 1.05, 1.07))),
               _record(CELLS[0], 2, 0.97), _record(CELLS[1], 2, 1.01),  # moving apart: one of two alike
               _record(CELLS[2], 2, 0.5, artifact="cache/artifacts/other"),  # another artifact: not the same
               _record(CELLS[2], 2, 0.5, host="laptop"), _record(CELLS[2], 2, 0.5, threads=2),
               *shown]  # the shown run itself: no move
    found = reruns(shown, history)
    assert [(r.run, r.cells, r.alike, r.held, r.intervals) for r in found] == \
        [(1, 3, 3, 0, 3), (2, 2, 1, 1, 2)]
    assert found[0].move == pytest.approx(0.06) and found[1].move == pytest.approx(-0.01, abs=0.002)
    assert reruns(shown, shown) == () and reruns([], history) == ()


def _store(path: Path, scales: list[float]) -> Path:
    """Runs of CELLS, the n-th with every p50 times scales[n]."""
    store = ResultStore(path)
    for scale in scales:
        run = store.begin_run("m.yaml", "vm", {}, started_at="2026-11-27T10:00:00")
        for cell in CELLS:
            store.put(_record(cell, run.id, scale))
    store.close()
    return path


@pytest.mark.parametrize(("scales", "said"), [
    ([1.0], None),
    ([0.99, 1.0], "Another run on the same host timed these artifacts: p50s -1.0% off this run's (the "
                  "median over its cells, 3 of 3 cells the same way); this run's p50 intervals held 3 of 3. "
                  "Speed-up"),
    ([1.07, 0.99, 1.0], "2 other runs on the same host timed these artifacts: p50s -1.0% to +7.0% off "
                        "this run's (each the median over a run's cells; in the largest move, 3 of 3 cells "
                        "the same way); this run's p50 intervals held 3 of 6: a machine's speed can move "
                        "between runs, which intervals from inside one run cannot see; the paired speed-ups "
                        "cancel what the cells share. Speed-up"),
])
def test_the_caption_says_how_far_other_runs_put_the_p50s(tmp_path: Path, scales: list[float],
                                                          said: str | None) -> None:
    report = load(_store(tmp_path / "r.sqlite", scales)).report
    text = caption(report.models[0])
    if said is None:
        assert "other run" not in text.lower() and report.models[0].reruns == ()
    else:
        assert said in text


def test_the_json_report_has_each_models_reruns(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    write_report(_store(tmp_path / "r.sqlite", [1.05, 1.0]), "json", tmp_path, Console())
    data = json.loads(capsys.readouterr().out)
    moved = Rerun(run=1, cells=3, move=pytest.approx(0.05), alike=3, held=0, intervals=3)
    assert data["reruns"] == {"tiny": [moved.to_json()]}

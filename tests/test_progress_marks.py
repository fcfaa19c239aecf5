"""The progress line of a finished cell marks a disturbed timing; a waiting phase is shown as plain text."""

from __future__ import annotations

import io
import re

from rich.console import Console

from bench_matrix.cell import Cell
from bench_matrix.progress import RunProgress, describe
from bench_matrix.store import CellRecord

CELL = Cell("tiny", "pytorch", "onnxruntime", "none", "fp32", "cpu")
METRICS = {"latency_ms": {"p50": 0.5, "p99": 0.9}, "throughput_sps": 1000.0, "size_bytes": 2**20, "mse": 0.01}


def line(metrics: dict) -> str:
    return describe(CellRecord(cell=CELL, status="ok", metrics=metrics))


def test_a_flagged_cell_says_it_was_disturbed_and_why():
    reason = "others took 35 % [steal 2 %]"
    flagged = line({**METRICS, "interference": {"flagged": True, "reason": reason}})
    assert flagged.endswith("  [yellow]~ disturbed: others took 35 % \\[steal 2 %][/]")
    unexplained = line({**METRICS, "interference": {"flagged": True, "reason": None}})
    assert unexplained.endswith("  [yellow]~ disturbed[/]")


def test_a_quiet_or_older_cell_has_no_mark():
    assert "disturbed" not in line({**METRICS, "interference": {"flagged": False, "reason": None}})
    assert "disturbed" not in line(METRICS)  # stored before interference was measured


def test_a_waiting_phase_shows_its_holder_verbatim():
    out = io.StringIO()
    with _progress(out, terminal=True) as progress:
        progress.step("tiny · onnxruntime none fp32")
        progress.phase("waiting for the timing phase of pid 12 of user a ([bold]x · tiny, since 17:50:02)")
    assert "[bold]x · tiny, since 17:50:02)" in out.getvalue()


def test_a_cell_calibrated_on_fewer_samples_than_asked_says_so():
    short = line({**METRICS, "calibration": {"asked": 100, "used": 40}})
    assert "! calibrated on 40 of the 100 samples asked for" in short
    assert "calibrated" not in line({**METRICS, "calibration": {"asked": 100, "used": 100}})
    assert "calibrated" not in line(METRICS)  # no calibration, or stored before it was recorded


def test_outside_a_terminal_each_step_and_phase_is_one_timed_line_and_rounds_after_the_first_are_not():
    out = io.StringIO()
    with _progress(out, terminal=False) as progress:
        progress.step("preparing model tiny")
        progress.phase("train · epoch 1/2 · loss 0.5 · about 3 s left")
        progress.step("tiny · measuring 2 cells in rounds")
        for number in (1, 2, 10):
            progress.phase(f"round {number}")
    lines = [line for line in out.getvalue().splitlines() if line]
    assert [line.split("] ", 1)[1] for line in lines] == [
        "preparing model tiny", "preparing model tiny · train · epoch 1/2 · loss 0.5 · about 3 s left",
        "tiny · measuring 2 cells in rounds", "tiny · measuring 2 cells in rounds · round 1"]
    assert all(re.fullmatch(r"\[ +\d+\.\d s\] .+", line) for line in lines), lines


def test_in_a_terminal_the_bar_alone_shows_the_steps():
    out = io.StringIO()
    with _progress(out, terminal=True) as progress:
        progress.step("preparing model tiny")
    assert not re.search(r"\[ +\d+\.\d s\] preparing", out.getvalue())


def _progress(out: io.StringIO, terminal: bool) -> RunProgress:
    """A run's progress of one cell, printed to `out` as in a terminal or not."""
    return RunProgress(Console(file=out, force_terminal=terminal, width=300), 1)

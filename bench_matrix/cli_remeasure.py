"""`compare --remeasure`: time both sides' artifacts again on this machine (bench_matrix/remeasure.py) and
give the two sides as remeasured, with each cell's paired ratio for `compare`."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import replace
from pathlib import Path

from rich.console import Console

from bench_matrix.errors import UserError
from bench_matrix.jobs.results import Measured
from bench_matrix.measure.stats import unpack_samples
from bench_matrix.measurement import Speedup
from bench_matrix.report.analysis.metric_change import Side
from bench_matrix.store import CellRecord


def remeasured(base: Side, new: Side, matrix: Path | None, workspace: Path
               ) -> tuple[Side, Side, dict[str, Speedup] | None]:
    """Both sides with the remeasured cells' figures and samples, and each one's base time ÷ new time (empty
    where the rounds could not pair them)."""
    from bench_matrix.executors import open_executor
    from bench_matrix.executors.local import probe
    from bench_matrix.matrix import load_matrix
    from bench_matrix.plan import resolve
    from bench_matrix.registry import available
    from bench_matrix.remeasure import BASE, NEW, Remeasure, twins
    from bench_matrix.workspace import Workspace

    console = Console(stderr=True)  # stdout carries the comparison
    found = twins(base.records, new.records)
    source = load_matrix(matrix or _matrix_of(new), backends=list(available()))
    for warning in source.warnings:
        console.print(f"warning: {warning}", markup=False, highlight=False, soft_wrap=True)
    ws = Workspace(workspace)
    executor = open_executor("local", ws)
    try:
        result = Remeasure(resolve(source, ws, probe), ws, executor, console, found).remeasure()
    finally:
        executor.close()
    console.print(f"remeasured {len(result.measured)} cells here, both sides in the same rounds",
                  highlight=False)
    for key, why in sorted(result.missing.items()):
        console.print(f"not remeasured (judged on the stored samples): {key}: {why}", highlight=False,
                      markup=False, soft_wrap=True)
    ratios = {key: sides[NEW].metrics.speedup or Speedup() for key, sides in result.measured.items()}
    return (_side(base, {key: sides[BASE] for key, sides in result.measured.items()}),
            _side(new, {key: sides[NEW] for key, sides in result.measured.items()}),
            ratios or None)


def _matrix_of(side: Side) -> Path:
    """The one matrix file the side's records came from."""
    named = sorted({record.matrix for record in side.records if record.matrix})
    if len(named) != 1 or not Path(named[0]).is_file():
        found = ", ".join(named) or "none"
        raise UserError(f"--remeasure: the new side's records name the matrix file(s) {found}, not one "
                        f"that is here; give the matrix the cells come from with --matrix FILE")
    return Path(named[0])


def _side(side: Side, measured: Mapping[str, Measured]) -> Side:
    """The side with its remeasured cells' figures (no speed-up: the pairing is the twins') and samples."""
    records = [_record(r, measured[r.cell.key]) if r.cell.key in measured else r for r in side.records]
    samples, batches = dict(side.samples), dict(side.batches)
    for key, found in measured.items():
        samples[key] = unpack_samples(found.samples["latency_ms"])
        if "batch_ms" in found.samples:
            batches[key] = unpack_samples(found.samples["batch_ms"])
    label = f"{side.label} (remeasured)" if measured else side.label
    return replace(side, label=label, records=records, samples=samples, batches=batches)


def _record(record: CellRecord, found: Measured) -> CellRecord:
    return replace(record, metrics=replace(found.metrics, speedup=None), env=found.env)

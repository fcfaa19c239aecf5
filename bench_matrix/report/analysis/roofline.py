"""A profiled cell on the roofline, from its stored fields only (docs/metrics.md §17): FLOP/s achieved at its
timed p50, its operational intensity, the bound the machine's peak puts on it and its share of that bound."""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

from bench_matrix.measure.peak import best_of
from bench_matrix.report.analysis.summary import Row, number

# the compute ceiling each precision is held to, in order of preference: a precision without its own measured
# peak (fp16 and bf16 through ONNX Runtime) is held to fp32's, which such a CPU computes it in
CEILINGS = {"fp32": ("fp32",), "int8": ("int8", "fp32"), "bf16": ("bf16", "fp32"), "fp16": ("fp16", "fp32")}


@dataclass(frozen=True)
class Roofline:
    """One cell against the machine: FLOP/s achieved, FLOP per byte, the compute ceiling (FLOP/s, and whose
    precision's it is) and the memory bandwidth (bytes/s)."""

    achieved: float
    intensity: float
    ceiling: float
    ceiling_of: str
    bandwidth: float

    @property
    def bound(self) -> float:
        """What the machine allows at this intensity: min(ceiling, intensity × bandwidth), FLOP/s."""
        return min(self.ceiling, self.intensity * self.bandwidth)

    @property
    def share(self) -> float:
        """Achieved ÷ bound."""
        return self.achieved / self.bound

    @property
    def memory_bound(self) -> bool:
        """Whether the bandwidth, not the compute ceiling, bounds the cell."""
        return self.intensity * self.bandwidth < self.ceiling

    @property
    def ridge(self) -> float:
        """The intensity where the bandwidth slope meets the ceiling, FLOP/byte."""
        return self.ceiling / self.bandwidth


def ceiling(precision: str, flops: Mapping[str, Any]) -> tuple[str, float] | None:
    """The peak FLOP/s a cell of `precision` is held to, and whose it is; None where none was measured."""
    for name in CEILINGS.get(precision, ("fp32",)):
        value = number(flops.get(name))
        if value is not None and math.isfinite(value) and value > 0:
            return name, value
    return None


def machine_key(others: Mapping[str, Any]) -> tuple[Any, ...]:
    """The machine a record's peak was measured on: its host, CPU and thread count."""
    return others.get("machine_host"), others.get("machine_cpu"), others.get("machine_threads")


def best_peaks(rows: Sequence[Row]) -> dict[tuple[Any, ...], dict[str, Any]]:
    """Per machine, the best of its records' peaks (measure.peak.best_of); a re-measured kept peak grows and
    keeps its first time, so of one such line the record with the most measurements holds the others."""
    lines: dict[tuple[Any, ...], dict[str, Any]] = {}
    for row in rows:
        peak = {k: v for k, v in row.record.metrics.others.items() if k.startswith("machine_")}
        if not isinstance(peak.get("machine_flops"), dict) or number(peak.get("machine_bandwidth")) is None:
            continue
        line = (*machine_key(peak), peak.get("machine_measured_at"))
        if _measurements(peak) >= _measurements(lines.get(line, {})):
            lines[line] = peak
    found: dict[tuple[Any, ...], dict[str, Any]] = {}
    for peak in lines.values():
        key = machine_key(peak)
        found[key] = best_of(found[key], peak) if key in found else peak
    return found


def _measurements(peak: Mapping[str, Any]) -> int:
    return int(peak.get("machine_measurements", 1)) if peak else 0


def model_work(rows: Sequence[Row]) -> dict[str, Any]:
    """The work of one inference of the rows' model: the `work_*` fields of the first record that has them
    (every cell of a model has the same: its fp32 ONNX graph's); empty where none has."""
    for row in rows:
        others = row.record.metrics.others
        flops, moved = number(others.get("work_flops")), number(others.get("work_bytes"))
        if flops is not None and moved and math.isfinite(flops) and math.isfinite(moved):
            return {k: v for k, v in others.items() if k.startswith("work_") and k != "work_reason"}
    return {}


def roofline(row: Row, among: Sequence[Row] = ()) -> Roofline | None:
    """The cell on the roofline: model work (its record's, else `among`'s) held to its machine's best peak in
    its and `among`'s records; None if work, peak or p50 (batch 1) is missing, or not finite and > 0."""
    latency, others = row.record.metrics.latency, row.record.metrics.others
    p50 = number(latency.p50) if latency else None
    if row.record.cell.target != "cpu":  # the peak is the CPU's
        return None
    work = model_work([row, *among])
    flops, moved = number(work.get("work_flops")), number(work.get("work_bytes"))
    peak = best_peaks([row, *among]).get(machine_key(others), {})
    bandwidth, peaks = number(peak.get("machine_bandwidth")), peak.get("machine_flops")
    found = ceiling(row.record.cell.precision, peaks) if isinstance(peaks, dict) else None
    figures = (flops, moved, bandwidth, p50)
    if found is None or not all(v is not None and math.isfinite(v) and v > 0 for v in figures):
        return None
    return Roofline(flops / (p50 / 1e3), flops / moved, found[1], found[0], bandwidth)

"""The profile section of a report, from stored records only: per profiled cell, its profiled time, the
profiler's overhead, its time's shares by operator kind × precision and its place on the roofline
(docs/metrics.md, Profiles and §17); the terminal shows the short form."""

from __future__ import annotations

import math
from typing import Any

from bench_matrix.op_profile import KINDS, PRECISIONS
from bench_matrix.report.analysis.roofline import best_peaks, model_work, roofline
from bench_matrix.report.analysis.summary import ModelSummary, Row, number
from bench_matrix.report.render.columns import DASH, METHOD, Column, fixed, sig
from bench_matrix.report.render.sections import Block

INTRO = ("Each cell's test sample ran under its runtime's own profiler after the rounds (docs/metrics.md, "
         "Profiles): its time by operator kind and the precision each operator ran at, as shares of the "
         "profiled time, and where its timed p50 puts it on the machine's roofline (§17).")
SHARE_NOTE = "share of the profiled time in operators of that kind (docs/metrics.md) run at that precision."
FLOAT_IN_INT8 = "float in int8 %"
FLOATS = ("fp32", "fp16", "bf16")
TOP_KINDS = 3


def profiled(model: ModelSummary) -> list[Row]:
    """The ok cells' rows with a profile, in the results table's order."""
    return [row for row in model.rows if isinstance(row.record.metrics.others.get("profile_operators"), list)]


def shares(row: Row) -> dict[tuple[str, str], float]:
    """The share of the cell's profiled time in each (kind, precision)."""
    found: dict[tuple[str, str], float] = {}
    for op in row.record.metrics.others["profile_operators"]:
        key = (op["kind"], op["precision"])
        found[key] = found.get(key, 0.0) + op["ms"]
    total = math.fsum(found.values())
    return {key: ms / total for key, ms in found.items()} if total > 0 else {}


def overhead(row: Row) -> float | None:
    """Profiled time per inference ÷ the timed p50 (batch 1); None where either is missing or not finite."""
    p50, ms = number(row.record.metrics.latency.p50), number(row.record.metrics.others.get("profile_ms"))
    ratio = ms / p50 if p50 and ms is not None else None
    return ratio if ratio is not None and math.isfinite(ratio) else None


def float_share(row: Row) -> float | None:
    """An int8 cell's share of time in operators that ran in floating point (None for other precisions)."""
    if row.record.cell.precision != "int8":
        return None
    return math.fsum(share for (_, precision), share in shares(row).items() if precision in FLOATS)


def top_kinds(row: Row) -> str:
    """The cell's largest kind × precision shares, e.g. 'conv fp32 71 %, matmul int8 12 %'."""
    ranked = sorted(shares(row).items(), key=lambda item: -item[1])[:TOP_KINDS]
    return ", ".join(f"{kind} {precision} {100 * share:.0f} %" for (kind, precision), share in ranked)


def _percent(value: float | None) -> str:
    return DASH if value is None else f"{100 * value:.1f}"


def _achieved(row: Row, rows: list[Row]) -> str:
    found = roofline(row, rows)
    return DASH if found is None else sig(found.achieved / 1e9, 3)


def _share(row: Row, rows: list[Row]) -> str:
    found = roofline(row, rows)
    if found is None:
        return DASH
    return f"{100 * found.share:.1f} ({'memory' if found.memory_bound else found.ceiling_of})"


def _roofline_columns(rows: list[Row]) -> list[Column]:
    return [Column("GFLOP/s", "FLOPs of one inference (its fp32 ONNX graph's) ÷ the timed p50 (batch 1).",
                   lambda row: _achieved(row, rows), "profile"),
            Column("Roofline %", "achieved FLOP/s ÷ min(the peak of the cell's precision, intensity × the "
                                 "stream bandwidth); in brackets what bounds it: a precision's peak or "
                                 "memory.",
                   lambda row: _share(row, rows), "profile")]


def _time_columns() -> list[Column]:
    return [METHOD,
            Column("Profiled ms", "sum of the operators' times per inference under the profiler.",
                   lambda row: sig(number(row.record.metrics.others.get("profile_ms")), 3), "profile"),
            Column("Overhead ×", "profiled ms ÷ the timed p50: how much the profiler slowed the cell.",
                   lambda row: fixed(overhead(row), 2), "profile")]


def _float_column(rows: list[Row]) -> list[Column]:
    int8 = any(row.record.cell.precision == "int8" for row in rows)
    return [Column(FLOAT_IN_INT8, "an int8 cell's share of time in operators that ran in floating point "
                                  "(fp32, fp16 or bf16).", lambda row: _percent(float_share(row)), "profile")
            ] if int8 else []


def columns(rows: list[Row]) -> list[Column]:
    """Method, time, overhead, a share column per (kind, precision) a row has, int8 cells' float share and the
    roofline's columns."""
    found = {key for row in rows for key in shares(row)}
    pairs = [(k, p) for k in KINDS for p in PRECISIONS if (k, p) in found]
    return [*_time_columns(),
            *(Column(f"{k} {p} %", SHARE_NOTE,
                     lambda row, key=(k, p): _percent(shares(row).get(key, 0.0)), "profile")
              for k, p in pairs),
            *_float_column(rows), *_roofline_columns(rows)]


def short_columns(rows: list[Row]) -> list[Column]:
    """The terminal's short form: time, overhead, the top kinds, int8 cells' float share and the roofline."""
    return [*_time_columns(),
            Column("Top kinds", f"the {TOP_KINDS} largest kind × precision shares.", top_kinds, "profile"),
            *_float_column(rows), *_roofline_columns(rows)]


def machine_lines(rows: list[Row]) -> list[str]:
    """The work of the model's inference and each machine's peak the rows were held to, a line each (none
    where absent)."""
    work = model_work(rows)
    return [*([work_line(work)] if work else []), *(peak_line(peak) for peak in best_peaks(rows).values())]


def work_line(work: dict[str, Any]) -> str:
    """'Work of one inference (...): 51.2 MFLOP, 1.2 MB moved at least (weights 1.0 MB), 42 FLOP/byte'."""
    flops, moved = work["work_flops"], work["work_bytes"]
    weights = work.get("work_weight_bytes", 0) / 1e6
    return (f"Work of one inference (its fp32 ONNX graph): {flops / 1e6:.4g} MFLOP, {moved / 1e6:.4g} MB "
            f"moved at least (weights {weights:.4g} MB), {flops / moved:.3g} FLOP/byte")


def peak_line(peak: dict[str, Any]) -> str:
    """'Peak of HOST (CPU), N thread(s), measured WHEN: fp32 99.8 GFLOP/s, int8 427 GOP/s; stream 31 GB/s',
    why a precision has none and what disturbed the measurement (best_peaks' values)."""
    flops = ", ".join(f"{name} {value / 1e9:.3g} G{'OP' if name == 'int8' else 'FLOP'}/s"
                      for name, value in peak["machine_flops"].items())
    count = peak.get("machine_measurements", 1)
    when = f"the best of {count} measurements" if count > 1 else f"measured {peak.get('machine_measured_at')}"
    reasons = "; ".join(f"{name}: {why}" for name, why in (peak.get("machine_reasons") or {}).items())
    disturbed = peak.get("machine_disturbed")
    return (f"Peak of {peak.get('machine_host')} ({peak.get('machine_cpu')}), {peak['machine_threads']} "
            f"thread(s), {when}: {flops}; stream {peak['machine_bandwidth'] / 1e9:.3g} GB/s"
            + (f" ({reasons})" if reasons else "")
            + (f"; measured while disturbed ({disturbed}): it may be low" if disturbed else ""))


def reasons(model: ModelSummary) -> list[str]:
    """Each ok cell's reason it has no profile, where it was asked for one, a profiled cell's reason it has
    no roofline, and a cell above its bound (the peak was measured low)."""
    found, rows = [], profiled(model)
    for row in model.rows:
        others = row.record.metrics.others
        for key, what in (("profile_reason", "Not profiled"), ("work_reason", "No work counted"),
                          ("machine_reason", "No peak")):
            if isinstance(others.get(key), str) and not (key == "work_reason" and model_work(rows)):
                found.append(f"{what}: {row.record.cell.label}: {others[key]}")
        placed = roofline(row, rows)
        if placed is not None and placed.share > 1:
            found.append(f"Above the roofline: {row.record.cell.label}: {placed.achieved / 1e9:.3g} GFLOP/s "
                         f"achieved, {placed.bound / 1e9:.3g} allowed: the machine's peak was measured low "
                         f"(disturbed?); delete the workspace's cache/peaks/ to measure it again")
    return found


def blocks(model: ModelSummary) -> list[Block]:
    """The model's "Where the time goes" block (none without a profile), its short form for the terminal."""
    found = profiled(model)
    if not found:
        return []
    lines = [*machine_lines(found), *reasons(model)]
    return [Block("Where the time goes", INTRO, columns(found), found, lines, brief=short_columns(found))]

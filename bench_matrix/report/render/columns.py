"""Number formatting and the results-table columns shared by the terminal, Markdown and HTML reports."""

from __future__ import annotations

import math
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from typing import Any

from bench_matrix.measure.metrics import DIRECTIONS, SNR_LIMIT_DB
from bench_matrix.measurement import Measurement
from bench_matrix.report.analysis.summary import (
    ModelSummary,
    Row,
    disturbed_phases,
    emulated,
    figure,
    metric,
    number,
    wide_phases,
)
from bench_matrix.store import CellRecord

DASH = "—"
MIB = 2**20
DELTA_NAMES = {"regression": "ΔMSE", "classification": "ΔTop-1"}
DIFFERENT_ENVIRONMENTS = "cells were not all measured in the same environment: compare their numbers with care."


def sig(value: float | None, digits: int) -> str:
    """`value` to `digits` significant digits, positional for 1e-4..1e6 (whole numbers kept whole), else exponent."""
    if value is None:
        return DASH
    if value == 0 or not math.isfinite(value):
        return "0" if value == 0 else str(value)
    magnitude = math.floor(math.log10(abs(value)))
    if -4 <= magnitude < 6:
        return f"{value:.{max(digits - 1 - magnitude, 0)}f}"
    return f"{value:.{digits - 1}e}"


def signed(value: float | None, digits: int) -> str:
    """Like `sig` with an explicit sign; exactly zero is "0"."""
    return sig(value, digits) if value is None or value <= 0 else "+" + sig(value, digits)


def fixed(value: float | None, decimals: int) -> str:
    return DASH if value is None else f"{value:.{decimals}f}"


def mib(size_bytes: float | None) -> str:
    return fixed(None if size_bytes is None else size_bytes / MIB, 2)


def times(value: float | None) -> str:
    return DASH if value is None else f"{value:.2f}×"


@dataclass(frozen=True)
class Column:
    """One results-table column: header ("\n" breaks it in the terminal), footnote, renderer and group (a
    narrow terminal splits the table by group; group "" is in every part)."""

    header: str
    note: str
    render: Callable[[Row], str]
    group: str
    optional: bool = False  # left out of a table where no row has a value

    @property
    def numeric(self) -> bool:
        return bool(self.group)


APPROXIMATE = " ~"  # after a timed figure: disturbed, or missed the ci_target asked for (docs/metrics.md §5)
EMULATED = " (emu)"  # after a timing measured on an emulated device (qemu-user): not the board's speed


def _timed(phase: str, read: Callable[[Measurement], Any]) -> Callable[[Row], str]:
    """A figure of a timed phase, marked APPROXIMATE when that phase was disturbed or missed the precision
    asked for (wide_phases), EMULATED when an emulated device measured it."""
    def render(row: Row) -> str:
        text = sig(figure(row.record, read), 3)
        marked = phase in disturbed_phases(row.record) or phase in wide_phases(row.record)
        text = text + APPROXIMATE if text != DASH and marked else text
        return text + EMULATED if text != DASH and emulated(row.record) else text
    return render


def _ci(row: Row) -> str:
    """Half the width of the p50's 95 % confidence interval, in % of the p50."""
    width = figure(row.record, lambda m: m.latency and m.latency.p50_ci_rel)
    return DASH if width is None else f"{width * 50:.1f}"


HOST = Column("Host", "the machine that measured the cell (shown when this model's cells come from more "
              "than one).", lambda r: r.record.host or DASH, "")
VERDICT = Column("Verdict", "against the model's requirements (see Verdict): pass; fail, with each "
                 "requirement missed and by how much; uncertain, with the timed figure whose 95 % interval "
                 "straddles its limit.", lambda r: r.verdict.short() if r.verdict is not None else DASH, "",
                 optional=True)
METHOD = Column("Method", "backend, strategy and precision (and target when not cpu) of the cell; "
                "(baseline): the model's baseline.",
                lambda r: r.record.cell.label + (" (baseline)" if r.is_baseline else ""), "")
SIZE, ACCURACY, SPEED, THROUGHPUT = "size", "accuracy", "speed", "throughput"
LEADING: tuple[Column, ...] = (
    METHOD,
    Column("Size\nMiB", "size of the converted model artifact on disk, in MiB (2^20 bytes).",
           lambda r: mib(figure(r.record, lambda m: m.size.bytes)), SIZE),
    Column("gzip\nMiB", "size of the artifact after gzip, in MiB: what weight sharing and pruning save in transfer.",
           lambda r: mib(figure(r.record, lambda m: m.size.gzip_bytes)), SIZE),
    Column("Size\nratio", "baseline size ÷ cell size: above 1× the cell's artifact is that many times smaller.",
           lambda r: times(r.size_ratio), SIZE),
    Column("Sparsity", "fraction of exactly-zero weights in the convolution and dense kernels of a fine-tuned "
           "(pruned or clustered) model.", lambda r: fixed(metric(r.record, "sparsity"), 3), SIZE, optional=True),
    Column("Clusters", "most distinct values held by any one weight kernel of a fine-tuned model (clustering "
           "keeps at most its number of clusters).", lambda r: fixed(metric(r.record, "clusters"), 0), SIZE,
           optional=True),
    Column("Fine-tune\ns", "seconds spent fine-tuning the source model (cached: shared by every backend of the "
           "strategy; included in convert_s).", lambda r: fixed(metric(r.record, "finetune_s"), 0), SIZE,
           optional=True),
)
TRAILING: tuple[Column, ...] = (
    Column("p50\nms", "median latency of one inference at batch 1, in milliseconds, over every round's "
                       "window; \"~\" after a timing figure marks a phase with too many windows disturbed "
                       "by other processes or CPU steal, or whose interval stayed wider than the "
                       "`ci_target` you set (records from before `asked`: than the target; older: no clean "
                       "attempt); treat it as approximate (the cell is listed under Disturbed or Wide); a "
                       "width nobody asked for is only its number in p50 CI ±%; "
                       "\"(emu)\": measured on an emulated device (qemu-user), "
                       "not the board's speed.",
           _timed("latency", lambda m: m.latency and m.latency.p50), SPEED),
    Column("p50 CI\n±%", "half the width of the 95 % interval a rerun's p50 falls in while the machine keeps "
           "this run's speed, from the spread of the per-round medians (older records: the p50's confidence "
           "interval from order statistics of the samples), in % of the p50; how far other runs on the same "
           "host put the same artifacts is in the caption.", _ci, SPEED, optional=True),
    Column("e2e p50\nms", "GPU cells: median latency at batch 1 including the host-to-device copy of the input "
           "and the copy of the outputs back (p50 ms counts the computation only, input already on the device).",
           _timed("latency_e2e", lambda m: m.latency_e2e and m.latency_e2e.p50), SPEED, optional=True),
    Column("p90\nms", "90th-percentile latency at batch 1, in milliseconds.",
           _timed("latency", lambda m: m.latency and m.latency.p90), SPEED),
    Column("p99\nms", "99th-percentile latency at batch 1, in milliseconds.",
           _timed("latency", lambda m: m.latency and m.latency.p99), SPEED),
    Column("Throughput\nsamples/s", "samples per second at the batch size given above the table.",
           _timed("throughput", lambda m: m.throughput.sps), THROUGHPUT),
    Column("Peak RSS\nMiB", "peak resident memory of the process that measured the cell, in MiB.",
           lambda r: fixed(figure(r.record, lambda m: m.memory.peak_rss_mb), 1), THROUGHPUT),
    Column("GPU\nMiB", "GPU cells: GPU memory the measuring process held after its runs, in MiB (see "
           "docs/metrics.md for how it is read).",
           lambda r: fixed(figure(r.record, lambda m: m.memory.gpu_mb), 0), THROUGHPUT, optional=True),
    Column("Speed-up", "baseline time ÷ cell time, paired round by round with its 95 % interval "
           "(docs/metrics.md §5; older records: baseline p50 ÷ cell p50): above 1× the cell is faster.",
           lambda r: times(r.speedup) + (f" ±{r.speedup_half:.1%}" if r.speedup_half is not None else ""),
           SPEED),
    Column("vs own\nfp32", "the same backend's fp32 cell (strategy none, same target) p50 ÷ cell p50: what the "
           "optimisation gains within one runtime.", lambda r: times(r.speedup_own_fp32), SPEED),
)


def percent(value: float | None) -> str:
    return DASH if value is None else f"{value * 100:.2f}"


def _points(value: float | None) -> str:
    """A difference of two fractions in percentage points, signed; exactly zero is "0.00"."""
    return DASH if value is None else "0.00" if value == 0 else f"{value * 100:+.2f}"


def _metric(key: str, render: Callable[[float | None], str]) -> Callable[[Row], str]:
    return lambda row: render(metric(row.record, key))


def _better(key: str) -> str:
    return "higher is better" if DIRECTIONS[key] == "higher" else "lower is better"


def _arrow(key: str) -> str:
    return "↑" if DIRECTIONS[key] == "higher" else "↓"


def _accuracy(header: str, key: str, what: str, render: Callable[[float | None], str]) -> Column:
    """A column of one accuracy metric, its direction in the header (↑/↓) and the footnote."""
    return Column(f"{header} {_arrow(key)}", f"{what}; {_better(key)}.", _metric(key, render), ACCURACY)


def _sig(digits: int) -> Callable[[float | None], str]:
    return lambda value: sig(value, digits)


def _fixed(decimals: int) -> Callable[[float | None], str]:
    return lambda value: fixed(value, decimals)


MAX_DIFF = _accuracy("max |Δ|\nvs base", "max_abs_diff_vs_baseline",
                     "largest absolute difference between the cell's and the baseline's outputs on the test "
                     "split",
                     _sig(3))
ACCURACY_COLUMNS: dict[str, tuple[Column, ...]] = {
    "regression": (
        _accuracy("MSE", "mse", "mean squared error on the normalised labels of the test split", _sig(4)),
        Column("ΔMSE", "cell MSE minus baseline MSE (positive = less accurate than the baseline).",
               lambda r: signed(r.mse_delta, 3), ACCURACY),
        _accuracy("MAE", "mae", "mean absolute error on the normalised labels of the test split", _sig(4)),
        MAX_DIFF),
    "classification": (
        _accuracy("Top-1\n%", "top1",
                  "share of test samples whose highest logit is their labelled class, in %", percent),
        Column("ΔTop-1\npp", "cell top-1 minus baseline top-1, in percentage points (negative = less "
               "accurate than the baseline).", lambda r: _points(r.accuracy_delta), ACCURACY),
        _accuracy("Top-5\n%", "top5", "share of test samples whose labelled class is among the k highest "
                  "logits, k = min(5, classes), in %", percent),
        _accuracy("Agreement\n%", "top1_agreement", "share of test samples whose highest logit is the class "
                  "the fp32 baseline's highest logit picks, in %", percent),
        MAX_DIFF),
    "none": (
        MAX_DIFF,
        _accuracy("Cosine", "cosine_similarity", "mean over test samples of the cosine between the cell's "
                  "and the baseline's outputs (all outputs of a sample flattened together; 1 = same "
                  "direction)",
                  _fixed(6)),
        _accuracy("SNR\ndB", "snr_db", "signal-to-noise ratio of the outputs against the baseline's, "
                  f"10·log10(Σ baseline² ÷ Σ difference²); {SNR_LIMIT_DB:.0f} = identical", _fixed(1)),
    ),
}


def model_columns(model: ModelSummary) -> tuple[Column, ...]:
    """Every column of the model's results table: its task's accuracy columns and its plugins' figures."""
    accuracy = ACCURACY_COLUMNS.get(model.task, ACCURACY_COLUMNS["none"])
    host = (HOST,) if len(hosts(model)) > 1 else ()
    return (LEADING[0], *host, VERDICT, *LEADING[1:], *accuracy, *output_columns(model),
            *_plugin_columns(model.rows), *TRAILING)


PER_OUTPUT = {"regression": (("MSE", "mse", 4), ("max |Δ|", "max_abs_diff_vs_baseline", 3)),
              "classification": (("max |Δ|", "max_abs_diff_vs_baseline", 3),),
              "none": (("max |Δ|", "max_abs_diff_vs_baseline", 3), ("Cosine", "cosine_similarity", 6))}


def output_columns(model: ModelSummary) -> list[Column]:
    """A model with several outputs: each output's own figures (the record's `per_output`), in order."""
    count = max((len(_outputs(row)) for row in model.rows), default=0)
    if count < 2:
        return []
    shapes = model.info.get("outputs") or []
    figures = PER_OUTPUT.get(model.task, PER_OUTPUT["none"])
    return [_output_column(index, shapes[index] if index < len(shapes) else None, *figure)
            for index in range(count) for figure in figures]


def _outputs(row: Row) -> tuple[Any, ...]:
    return row.record.metrics.task.per_output or ()


def _output_column(index: int, shape: Any, header: str, key: str, digits: int) -> Column:
    """One figure of output `index` (its shape, per sample, in the header) from the record's `per_output`."""
    dims = "×".join(str(d) for d in shape) if isinstance(shape, list) and shape else "scalar"

    def render(row: Row) -> str:
        outputs = _outputs(row)
        value = outputs[index].get(key) if index < len(outputs) and isinstance(outputs[index], dict) else None
        return sig(number(value), digits)
    return Column(f"{header} {_arrow(key)}\nout {index + 1} ({dims})",
                  f"`{key}` of output {index + 1} alone (per sample {dims}); {_better(key)}.",
                  render, ACCURACY, optional=True)


def hosts(model: ModelSummary) -> tuple[str, ...]:
    """The distinct hosts that measured (or skipped, or failed) the model's cells; "unknown" where unnamed."""
    records = (*(r.record for r in model.rows), *model.skipped, *model.failed)
    return tuple(sorted({r.host or "unknown" for r in records}))


def cell_names(model: ModelSummary, records: Iterable[CellRecord]) -> list[str]:
    """The cells' labels, each with "on HOST" when the model's cells come from more than one host."""
    several = len(hosts(model)) > 1
    return [r.cell.label + (f" on {r.host or 'unknown'}" if several else "") for r in records]


def _plugin_columns(rows: Iterable[Row]) -> list[Column]:
    """One column per metric-plugin figure ("NAME.FIGURE" keys) that some row holds."""
    keys = sorted({key for r in rows for key, value in r.record.metrics.others.items()
                   if "." in key and number(value) is not None})
    return [Column(key, "figure `{1}` of the metric plugin `{0}` (its direction: see the plugin)."
                   .format(*key.split(".", 1)), _metric(key, _sig(4)), ACCURACY) for key in keys]


def shown(columns: Iterable[Column], rows: Iterable[Row]) -> list[Column]:
    """The columns worth a place in a table of these rows: optional ones only where some row has a value."""
    rows = list(rows)
    return [c for c in columns if not c.optional or any(c.render(r) != DASH for r in rows)]

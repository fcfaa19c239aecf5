"""The profile section's plots, from stored records only: per model each profiled cell's time by operator
kind × precision (stacked bars: floating-point parts in blues and greens, int8 in oranges) and the roofline
of its cells (log-log: the bandwidth slope, a ceiling per measured precision, each cell a point)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from bench_matrix.op_profile import KINDS, PRECISIONS
from bench_matrix.report.analysis.roofline import Roofline, best_peaks, machine_key, roofline
from bench_matrix.report.analysis.summary import ModelSummary, Row
from bench_matrix.report.render.plots import MARKERS, Plot, file_stem, new_figure, save_figure
from bench_matrix.report.render.sections import Section
from bench_matrix.scenarios.profile.report import blocks, profiled

FAMILIES = {"fp32": "Blues", "fp16": "Greens", "bf16": "Purples", "int8": "Oranges", "other": "Greys"}
CEILING_STYLES = {"fp32": "-", "int8": "--", "bf16": "-.", "fp16": ":"}
BAR_IN, BARS_TOP = 0.35, 1.4  # inches per cell's bar, and around the bars


def profile_plots(model: ModelSummary, folder: Path) -> list[Plot]:
    """The model's time-by-kind bars and its roofline, where its cells have what they need."""
    rows = profiled(model)
    if not rows:
        return []
    folder.mkdir(parents=True, exist_ok=True)
    stem = file_stem(model.name)
    plots = [Plot("profile", f"Where the time goes: {model.name}", folder / f"profile-{stem}.png",
                  f"Profiled time per inference of each cell of {model.name} by operator kind and precision")]
    save_figure(time_figure(model, rows), plots[0].path)
    placed = [(row, found) for row in rows if (found := roofline(row, rows)) is not None]
    if placed:
        plots.append(Plot("roofline", f"Roofline: {model.name}", folder / f"roofline-{stem}.png",
                          f"Achieved GFLOP/s of each profiled cell of {model.name} against the machine's "
                          f"bandwidth slope and compute ceilings"))
        save_figure(roofline_figure(model, placed), plots[1].path)
    return plots


def colour(kind: str, precision: str) -> Any:
    """The kind's shade in its precision's colour family (fp32 blues, int8 oranges, ...)."""
    from matplotlib import colormaps

    family = colormaps[FAMILIES.get(precision, "Greys")]
    return family(0.95 - 0.6 * KINDS.index(kind) / max(len(KINDS) - 1, 1) if kind in KINDS else 0.5)


def time_figure(model: ModelSummary, rows: list[Row]) -> Any:
    """Horizontal bars, one per cell, its profiled ms per inference split by kind × precision (the legend's
    order: by precision, then kind)."""
    figure = new_figure(BARS_TOP + BAR_IN * len(rows))
    figure.subplots_adjust(left=0.25, right=0.75, top=1 - 0.45 / figure.get_figheight(),
                           bottom=0.75 / figure.get_figheight())
    axes = figure.add_subplot()
    times = [_times(row) for row in reversed(rows)]
    keys = sorted({key for found in times for key in found},
                  key=lambda key: (PRECISIONS.index(key[1]) if key[1] in PRECISIONS else len(PRECISIONS),
                                   KINDS.index(key[0])))
    left = np.zeros(len(rows))
    for key in keys:
        widths = np.array([found.get(key, 0.0) for found in times])
        axes.barh(range(len(rows)), widths, left=left, color=colour(*key), edgecolor="white", linewidth=0.5,
                  label=f"{key[0]} {key[1]}")
        left += widths
    axes.set_yticks(range(len(rows)), [row.record.cell.label for row in reversed(rows)], fontsize=8)
    axes.set_xlabel("ms per inference under the profiler (batch 1)", fontsize=8)
    axes.set_title(f"{model.name}: where the time goes", fontsize=9, loc="left")
    axes.legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.02, 1.0), frameon=False)
    return figure


def _times(row: Row) -> dict[tuple[str, str], float]:
    found: dict[tuple[str, str], float] = {}
    for op in row.record.metrics.others["profile_operators"]:
        key = (op["kind"] if op["kind"] in KINDS else "other", op["precision"])
        found[key] = found.get(key, 0.0) + op["ms"]
    return found


def roofline_figure(model: ModelSummary, placed: list[tuple[Row, Roofline]]) -> Any:
    """Log-log: GFLOP/s against FLOP/byte; the bandwidth slope up to each precision's ceiling, each cell's
    point labelled with its share of its bound."""
    figure = new_figure(5.0)
    axes = figure.add_axes((0.1, 0.12, 0.55, 0.78))
    first = placed[0][1]
    intensities = [found.intensity for _, found in placed]
    ceilings = {found.ceiling_of: found.ceiling for _, found in placed}
    ceilings.update(_all_ceilings([row for row, _ in placed]))
    low = min(min(intensities), min(c / first.bandwidth for c in ceilings.values())) / 8
    high = max(max(intensities), max(c / first.bandwidth for c in ceilings.values())) * 8
    for name, peak in sorted(ceilings.items(), key=lambda item: -item[1]):
        ridge = peak / first.bandwidth
        axes.plot([low, ridge, high], [low * first.bandwidth / 1e9, peak / 1e9, peak / 1e9],
                  CEILING_STYLES.get(name, "-"), color="#555555", linewidth=1.0)
        unit = "GOP/s" if name == "int8" else "GFLOP/s"
        axes.annotate(f"{name} peak {peak / 1e9:.3g} {unit}", (high, peak / 1e9), fontsize=7, ha="right",
                      va="bottom")
    axes.annotate(f"stream {first.bandwidth / 1e9:.3g} GB/s", (low * 1.5, low * 1.5 * first.bandwidth / 1e9),
                  fontsize=7, rotation=0, va="bottom")
    for row, found in placed:
        axes.plot(found.intensity, found.achieved / 1e9, MARKERS.get(row.record.cell.precision, "o"),
                  label=f"{row.record.cell.label}: {100 * found.share:.1f} % of its bound", markersize=6)
    axes.set_xscale("log")
    axes.set_yscale("log")
    axes.set_xlabel("operational intensity, FLOP per byte (fp32 graph)", fontsize=8)
    axes.set_ylabel("GFLOP/s achieved at the timed p50", fontsize=8)
    axes.set_title(f"{model.name}: roofline", fontsize=9, loc="left")
    axes.legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.02, 1.0), frameon=False)
    return figure


def _all_ceilings(rows: list[Row]) -> dict[str, float]:
    """Every precision's best measured peak of the first row's machine, FLOP/s."""
    peak = best_peaks(rows).get(machine_key(rows[0].record.metrics.others), {})
    return {name: float(value) for name, value in (peak.get("machine_flops") or {}).items() if value > 0}


SECTION = Section(blocks, profile_plots)  # the profile scenario's section

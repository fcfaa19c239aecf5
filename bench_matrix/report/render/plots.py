"""Report plots (matplotlib, Agg): per model a Pareto chart, latency distributions and each scenario's plots.

Figures are drawn on an Agg canvas without pyplot (no display, no global state) and saved without a Software
tag, so the same records give the same bytes; matplotlib is imported only when a plot is drawn."""

from __future__ import annotations

import hashlib
import math
import re
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from bench_matrix.report.analysis.pareto import Point, accuracy_metric, points
from bench_matrix.report.analysis.summary import ModelSummary, disturbed_phases, wide_phases
from bench_matrix.report.render import pareto_marks
from bench_matrix.report.render.columns import APPROXIMATE, cell_names, sig
from bench_matrix.report.render.pareto_layout import Box, place_labels, reference_sizes
from bench_matrix.store import CellRecord

DPI = 110
WIDTH_IN = 10.5
FONT = 8.0
AREA_MAX, AREA_MIN = 420.0, 16.0  # marker area (pt²) of the largest artifact, and the floor for tiny ones
MARKERS = {"fp32": "o", "fp16": "s", "bf16": "D", "int8": "^"}
SPARE_MARKERS = ("v", "P", "X", "h", "<", ">", "p", "*")
AXIS_NAMES = {"mse": "test MSE on the normalised labels", "top1": "test top-1 accuracy, %",
              "cosine_similarity": "cosine similarity to the fp32 baseline's outputs"}
SCALES = {"top1": 100.0}  # shown in %
SAFE_NAME = re.compile(r"[A-Za-z0-9][A-Za-z0-9_.+-]{0,99}")
# Pareto chart layout, inches: margins, axes, the legend column right of the axes and the cell key below
TOP, LEFT, AXES_W, AXES_H_MIN, LEGEND_GAP = 0.5, 0.95, 6.5, 4.4, 0.2
BELOW_AXES, KEY_HEADER, KEY_ROW, BOTTOM = 0.6, 0.3, 0.17, 0.15
LABEL_GAP = 2.0  # pixels between a marker and its number
# latency chart: inches per cell row, above and below the rows
ROW_IN, LATENCY_TOP, LATENCY_BOTTOM = 0.3, 0.55, 0.75


@dataclass(frozen=True)
class Plot:
    """A PNG written for a model's page: what it shows (`kind`: pareto, latency, or a scenario's), caption,
    alt text."""

    kind: str
    title: str
    path: Path
    alt: str


@dataclass(frozen=True)
class Style:
    """Colour per backend and marker per precision, shared by a model's charts."""

    colours: dict[str, Any]
    markers: dict[str, str]


def model_plots(model: ModelSummary, samples: Mapping[int, np.ndarray], folder: Path) -> list[Plot]:
    """Draw the model's plots that have data into `folder` (created when needed): the Pareto chart, the
    latency distributions (cells with raw `samples`, by record id)."""
    if not model.rows:
        return []
    folder.mkdir(parents=True, exist_ok=True)
    stem = file_stem(model.name)
    found = [pareto_plot(model, folder / f"pareto-{stem}.png"),
             latency_plot(model, samples, folder / f"latency-{stem}.png")]
    return [plot for plot in found if plot is not None]


def _name(model: ModelSummary, record: CellRecord) -> str:
    """The cell's label, with its host when the model's cells come from several."""
    return cell_names(model, [record])[0]


def file_stem(name: str) -> str:
    """`name` where it is a safe file name as it is, else its safe characters and a digest of it (unique)."""
    if SAFE_NAME.fullmatch(name):
        return name
    slug = re.sub(r"[^A-Za-z0-9_.+-]+", "_", name)[:60].strip("._-") or "model"
    return f"{slug}-{hashlib.sha256(name.encode()).hexdigest()[:8]}"


def pareto_plot(model: ModelSummary, path: Path) -> Plot | None:
    """The Pareto chart, when at least two ok cells have a p50 latency and an accuracy."""
    found, left_out = points(model)
    if len(found) < 2:
        return None
    save_figure(pareto_figure(model, found), path)
    name, higher = accuracy_metric(model)
    optimal = ", ".join(_name(model, p.record) for p in found if p.optimal)
    alt = (f"Pareto chart of {model.name}: p50 latency in ms against {AXIS_NAMES.get(name, name)} "
           f"({'higher' if higher else 'lower'} is better) for {len(found)} cells, marker area proportional "
           f"to artifact size. Pareto-optimal: {optimal}.")
    if any(p.verdict for p in found):
        passing = ", ".join(_name(model, p.record) for p in found if p.verdict == "pass") or "none"
        alt += f" Passing the requirements (green rings): {passing}."
    if left_out:
        alt += f" Not shown (no latency or {name}): {', '.join(_name(model, r) for r in left_out)}."
    return Plot("pareto", f"{model.name}: latency against accuracy", path, alt)


def latency_plot(model: ModelSummary, samples: Mapping[int, np.ndarray], path: Path) -> Plot | None:
    """Box plots of the raw latencies of every ok cell that has samples, fastest median first."""
    timed = [(row.record, np.asarray(samples[row.record.id], dtype=np.float64)) for row in model.rows
             if row.record.id is not None and np.size(samples.get(row.record.id, ())) > 0]
    if not timed:
        return None
    timed.sort(key=lambda item: (float(np.median(item[1])), item[0].cell.key))
    save_figure(latency_figure(model, timed), path)
    (fast, fast_s), (slow, slow_s) = timed[0], timed[-1]
    alt = (f"Latency distribution of {len(timed)} cells of {model.name} at batch 1 from their raw samples "
           f"(box: 25th-75th percentile, line: median, whiskers: 1st-99th percentile), fastest median first: "
           f"{_name(model, fast)} {sig(float(np.median(fast_s)), 3)} ms to {_name(model, slow)} "
           f"{sig(float(np.median(slow_s)), 3)} ms.")
    shown = {record.id for record, _ in timed}
    missing = [_name(model, row.record) for row in model.rows if row.record.id not in shown]
    if missing:
        alt += f" Not shown (no raw samples stored): {', '.join(missing)}."
    return Plot("latency", f"{model.name}: latency distribution per cell", path, alt)


def pareto_figure(model: ModelSummary, found: Sequence[Point]) -> Any:
    """Latency (x) against accuracy (y), area by size, colour by backend, marker by precision; numbered points
    listed in a key below the axes, the legend beside them."""
    style = model_style(model)
    figure = new_figure(6.0)
    legend = _pareto_legend(figure, found, style)
    extent = legend.get_window_extent(figure.canvas.get_renderer())
    width = max(WIDTH_IN, LEFT + AXES_W + LEGEND_GAP + extent.width / DPI + 0.1)
    entries = [(f"{p.number}: {_plain(_name(model, p.record))}{' *' if p.optimal else ''}"
                f"{APPROXIMATE if _approximate(p.record) else ''}{pareto_marks.mark(p)}", p.optimal)
               for p in found]
    column_w = max(_text_size(figure, text, FONT, bold)[0] for text, bold in entries) / DPI + 0.3
    rows = -(-len(entries) // max(1, min(len(entries), int((width - LEFT) // column_w))))
    axes_h = max(AXES_H_MIN, extent.height / DPI)
    height = TOP + axes_h + BELOW_AXES + KEY_HEADER + rows * KEY_ROW + BOTTOM
    figure.set_size_inches(width, height)
    legend.set_bbox_to_anchor((LEFT + AXES_W + LEGEND_GAP, height - TOP), transform=figure.dpi_scale_trans)
    axes = figure.add_axes((LEFT / width, (height - TOP - axes_h) / height, AXES_W / width, axes_h / height))
    scale = SCALES.get(accuracy_metric(model)[0], 1.0)
    _draw_points(axes, found, style, scale)
    _label_axes(axes, model)
    _number_points(axes, found, scale)
    _draw_key(figure, entries, height - TOP - axes_h - BELOW_AXES, column_w, rows, pareto_marks.note(found))
    return figure


def _draw_key(figure: Any, entries: Sequence[tuple[str, bool]], top: float, column_w: float, rows: int,
              marks: list[str]) -> None:
    """The "number: cell" list below the axes, column by column from `top` (inches), optimal cells bold."""
    notes = ["number on the chart, backend strategy precision [target]", "* Pareto-optimal (bold, ringed)",
             *marks]
    if any(text.endswith(APPROXIMATE) for text, _ in entries):
        notes.append("~ latency disturbed or wider than the ci_target asked (see the page)")
    figure.text(LEFT, top, "Cells: " + ";  ".join(notes), fontsize=FONT, transform=figure.dpi_scale_trans,
                va="top", style="italic")
    for k, (text, bold) in enumerate(entries):
        column, row = divmod(k, rows)
        figure.text(LEFT + column * column_w, top - KEY_HEADER - row * KEY_ROW, text, fontsize=FONT,
                    fontweight="bold" if bold else "normal", transform=figure.dpi_scale_trans, va="top")


def _draw_points(axes: Any, found: Sequence[Point], style: Style, scale: float) -> None:
    """The markers, CI bars and the front's staircase (y values times `scale`); limits frozen afterwards."""
    _draw_intervals(axes, found, style, scale)
    largest = _largest(found)
    for (precision, optimal), group in _groups(found).items():
        axes.scatter([p.latency_ms for p in group], [p.accuracy * scale for p in group],
                     s=[marker_area(p.size_bytes, largest) for p in group],
                     c=[style.colours[p.record.cell.backend] for p in group], marker=style.markers[precision],
                     alpha=0.9 if optimal else 0.55, edgecolors="black" if optimal else "white",
                     linewidths=1.6 if optimal else 0.6, zorder=4 if optimal else 3)
    pareto_marks.draw(axes, found, scale, lambda p: marker_area(p.size_bytes, largest))
    front = sorted((p.latency_ms, p.accuracy * scale) for p in found if p.optimal)
    axes.step([x for x, _ in front], [y for _, y in front], where="post", color="black", linewidth=1.0,
              linestyle="--", zorder=1)
    _scale(axes, "x", [p.latency_ms for p in found])
    _scale(axes, "y", [p.accuracy * scale for p in found])
    axes.margins(0.08)
    axes.autoscale_view()
    axes.set_xlim(axes.get_xlim())
    axes.set_ylim(axes.get_ylim())


def _label_axes(axes: Any, model: ModelSummary) -> None:
    name, higher = accuracy_metric(model)
    axes.grid(True, which="major", color="0.9", linewidth=0.8)
    axes.set_axisbelow(True)
    axes.tick_params(labelsize=FONT)
    axes.set_xlabel("p50 latency of one inference at batch 1, ms (lower is better)", fontsize=FONT + 1)
    axes.set_ylabel(f"{AXIS_NAMES.get(name, name)} ({'higher' if higher else 'lower'} is better)",
                    fontsize=FONT + 1)
    axes.set_title(f"{_plain(model.name)}: latency against accuracy, marker area ∝ artifact size",
                   fontsize=FONT + 2, loc="left")


def _draw_intervals(axes: Any, found: Sequence[Point], style: Style, scale: float) -> None:
    """The p50's confidence interval as horizontal error bars, one call per backend colour."""
    for backend, colour in style.colours.items():
        bars = [p for p in found if p.ci is not None and p.record.cell.backend == backend]
        if bars:
            below, above = [p.latency_ms - p.ci[0] for p in bars], [p.ci[1] - p.latency_ms for p in bars]
            axes.errorbar([p.latency_ms for p in bars], [p.accuracy * scale for p in bars],
                          xerr=[below, above], fmt="none", ecolor=colour, elinewidth=0.9, capsize=2.5,
                          zorder=2)


def _groups(found: Sequence[Point]) -> dict[tuple[str, bool], list[Point]]:
    """The points by (precision, optimal), in a fixed order: one scatter call each."""
    groups: dict[tuple[str, bool], list[Point]] = {}
    for p in sorted(found, key=lambda p: (p.record.cell.precision, p.optimal, p.number)):
        groups.setdefault((p.record.cell.precision, p.optimal), []).append(p)
    return groups


def _number_points(axes: Any, found: Sequence[Point], scale: float) -> None:
    """Write each point's number beside it where it overlaps no other number, marker or the axes' edge (y
    values times `scale`)."""
    from matplotlib.patheffects import withStroke

    renderer = axes.figure.canvas.get_renderer()
    largest = _largest(found)
    anchors = [tuple(axes.transData.transform((p.latency_ms, p.accuracy * scale))) for p in found]
    radii = [renderer.points_to_pixels(math.sqrt(marker_area(p.size_bytes, largest)) / 2) for p in found]
    sizes = [tuple(v + 2 for v in _text_size(axes.figure, str(p.number), FONT, p.optimal)) for p in found]
    x0, y0, x1, y1 = axes.bbox.extents
    centres = place_labels(anchors, radii, sizes, Box(x0 + 2, y0 + 2, x1 - 2, y1 - 2), LABEL_GAP)
    to_points = 72.0 / DPI
    for p, (ax, ay), (cx, cy), radius, size in zip(found, anchors, centres, radii, sizes):
        box = Box(cx - size[0] / 2, cy - size[1] / 2, cx + size[0] / 2, cy + size[1] / 2)
        far = box.distance(ax, ay) > radius + LABEL_GAP + 1.0  # not in the first ring: a leader line
        axes.annotate(str(p.number), (p.latency_ms, p.accuracy * scale),
                      xytext=((cx - ax) * to_points, (cy - ay) * to_points), textcoords="offset points",
                      ha="center", va="center", fontsize=FONT, zorder=5,
                      fontweight="bold" if p.optimal else "normal",
                      path_effects=[withStroke(linewidth=2.5, foreground="white")],
                      arrowprops=dict(arrowstyle="-", color="0.45", linewidth=0.6, shrinkA=0,
                                      shrinkB=radius * to_points) if far else None)


def _pareto_legend(figure: Any, found: Sequence[Point], style: Style) -> Any:
    """One legend in sections: backend colours, precision markers, reference sizes, the front and the CI."""
    from matplotlib.lines import Line2D

    def entry(label: str, **kwargs: Any) -> tuple[Any, str]:
        return Line2D([], [], linestyle=kwargs.pop("linestyle", ""), **kwargs), label

    backends = sorted({p.record.cell.backend for p in found})
    precisions = sorted({p.record.cell.precision for p in found})
    sizes = [p.size_bytes for p in found if p.size_bytes]
    items = [entry("Backend (colour)")]
    items += [entry(b, marker="o", color=style.colours[b], markersize=7) for b in backends]
    items += [entry("Precision (marker)")] + [entry(p, marker=style.markers[p], color="0.4", markersize=7)
                                               for p in precisions]
    if sizes:
        items += [entry("Artifact size (area)")] + [
            entry(f"{s / 2**20:g} MiB", marker="o", color="0.75", markeredgecolor="0.4",
                  markersize=math.sqrt(marker_area(s, max(sizes)))) for s in reference_sizes(sizes)]
    items += [entry("Pareto front"),
              entry("optimal (ringed, bold number)", marker="o", markerfacecolor="white",
                    markeredgecolor="black", markeredgewidth=1.6, markersize=8),
              entry("front line", color="black", linestyle="--", linewidth=1.0)]
    if any(p.ci for p in found):
        items.append(entry("p50 95 % CI", color="0.4", marker="|", markersize=8, linestyle="-"))
    items += pareto_marks.legend_entries(found)
    legend = figure.legend([h for h, _ in items], [label for _, label in items], loc="upper left",
                           fontsize=FONT, frameon=False, handletextpad=0.6, borderaxespad=0.0)
    headers = {"Backend (colour)", "Precision (marker)", "Artifact size (area)", "Pareto front",
               pareto_marks.HEADER}
    for text in legend.get_texts():
        if text.get_text() in headers:
            text.set_fontweight("bold")
    return legend


def latency_figure(model: ModelSummary, timed: Sequence[tuple[CellRecord, np.ndarray]]) -> Any:
    """One horizontal box per cell (fastest median on top), cell labels left, sample counts right."""
    style = model_style(model)
    labels = [_plain(_name(model, r)) + (APPROXIMATE if _approximate(r) else "") for r, _ in timed]
    counts = [f"n = {len(s):,}" for _, s in timed]
    height = max(2.4, LATENCY_TOP + len(timed) * ROW_IN + LATENCY_BOTTOM)
    figure = new_figure(height)
    left = max(_text_size(figure, t, FONT, False)[0] for t in labels) / DPI + 0.3
    right = max(_text_size(figure, t, FONT, False)[0] for t in counts) / DPI + 0.3
    rows_h = height - LATENCY_TOP - LATENCY_BOTTOM
    axes = figure.add_axes((left / WIDTH_IN, LATENCY_BOTTOM / height, (WIDTH_IN - left - right) / WIDTH_IN,
                            rows_h / height))
    ys = np.arange(len(timed))[::-1].astype(float)
    p1, p25, p50, p75, p99 = np.array([np.percentile(s, [1, 25, 50, 75, 99]) for _, s in timed]).T
    colours = [style.colours[r.cell.backend] for r, _ in timed]
    axes.hlines(ys, p1, p99, colors=colours, linewidth=1.0, zorder=2)
    axes.vlines(np.concatenate([p1, p99]), np.tile(ys - 0.15, 2), np.tile(ys + 0.15, 2),
                colors=colours + colours, linewidth=1.0, zorder=2)
    axes.barh(ys, p75 - p25, left=p25, height=0.55, color=colours, alpha=0.8, edgecolor="0.25",
              linewidth=0.6, zorder=3)
    axes.vlines(p50, ys - 0.275, ys + 0.275, colors="black", linewidth=1.6, zorder=4)
    _scale(axes, "x", list(p1) + list(p99))
    axes.set_ylim(-0.6, len(timed) - 0.4)
    axes.set_yticks(ys, labels, fontsize=FONT)
    axes.secondary_yaxis("right").set_yticks(ys, counts, fontsize=FONT)
    axes.tick_params(axis="x", labelsize=FONT)
    axes.grid(True, axis="x", which="major", color="0.9", linewidth=0.8)
    axes.set_axisbelow(True)
    axes.set_xlabel("latency of one inference at batch 1, ms (box: 25th-75th percentile, black line: median, "
                    "whiskers: 1st-99th percentile)", fontsize=FONT + 1)
    approximate = any(APPROXIMATE in t for t in labels)
    marked = "; ~ latency disturbed or wider than the ci_target asked" if approximate else ""
    axes.set_title(f"{_plain(model.name)}: latency per cell from the raw samples, fastest median on top"
                   f"{marked}", fontsize=FONT + 2, loc="left")
    return figure


def model_style(model: ModelSummary) -> Style:
    """A colour per backend (tab10, tab20 beyond ten) and a marker per precision, over all ok cells."""
    from matplotlib import colormaps

    backends = sorted({row.record.cell.backend for row in model.rows})
    palette = colormaps["tab10" if len(backends) <= 10 else "tab20"].colors
    precisions = sorted({row.record.cell.precision for row in model.rows})
    spare = iter(SPARE_MARKERS * (1 + len(precisions) // len(SPARE_MARKERS)))
    return Style(colours={b: palette[k % len(palette)] for k, b in enumerate(backends)},
                 markers={p: MARKERS.get(p) or next(spare) for p in precisions})


def _largest(found: Sequence[Point]) -> float | None:
    return max((p.size_bytes for p in found if p.size_bytes), default=None)


def marker_area(size_bytes: float | None, largest: float | None) -> float:
    """Marker area in pt², proportional to the artifact size (a floor keeps tiny or unknown sizes visible)."""
    if not size_bytes or not largest:
        return AREA_MIN
    return max(AREA_MAX * size_bytes / largest, AREA_MIN)


def _scale(axes: Any, axis: str, values: Sequence[float]) -> None:
    """Log scale with 1-2-5 ticks when the positive values span more than 10x, else linear without offset."""
    from matplotlib.ticker import FuncFormatter, LogLocator, NullFormatter, ScalarFormatter

    target = axes.xaxis if axis == "x" else axes.yaxis
    low, high = min(values), max(values)
    if low > 0 and high / low > 10:
        (axes.set_xscale if axis == "x" else axes.set_yscale)("log")
        decades = math.log10(high / low)
        target.set_major_locator(LogLocator(subs=(1.0, 2.0, 5.0) if decades <= 3 else (1.0,)))
        target.set_major_formatter(FuncFormatter(lambda value, _: f"{value:g}"))
        target.set_minor_formatter(NullFormatter())
    else:
        target.set_major_formatter(ScalarFormatter(useOffset=False))


def _approximate(record: CellRecord) -> bool:
    """Whether the cell's latency is marked approximate in the results table (disturbed, or wider than the
    ci_target asked)."""
    return "latency" in disturbed_phases(record) or "latency" in wide_phases(record)


def _plain(text: str) -> str:
    """`text` with "$" escaped, so matplotlib never reads it as mathtext."""
    return text.replace("$", r"\$")


def _text_size(figure: Any, text: str, size: float, bold: bool) -> tuple[float, float]:
    """Width and height in pixels of `text` drawn at `size` points, as matplotlib lays it out."""
    probe = figure.text(0, 0, text, fontsize=size, fontweight="bold" if bold else "normal")
    extent = probe.get_window_extent(figure.canvas.get_renderer())
    probe.remove()
    return extent.width, extent.height


def new_figure(height_in: float) -> Any:
    """A figure on an Agg canvas (no pyplot, no display)."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    figure = Figure(figsize=(WIDTH_IN, height_in), dpi=DPI)
    FigureCanvasAgg(figure)
    return figure


def save_figure(figure: Any, path: Path) -> None:
    figure.savefig(path, dpi=DPI, metadata={"Software": None})

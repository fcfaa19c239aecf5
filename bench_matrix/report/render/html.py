"""The report as one self-contained HTML file: the models overview, each model's sortable results table, plots
(inline), each scenario's section, skipped and failed cells grouped by reason, notes and the environment."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path

from bench_matrix.report.analysis.noise import noise
from bench_matrix.report.analysis.summary import Environment, ModelSummary, Report, headline
from bench_matrix.report.render.columns import DIFFERENT_ENVIRONMENTS, cell_names, model_columns, shown
from bench_matrix.report.render.html_parts import SCRIPT, STYLE, Html, esc, plot_html, table
from bench_matrix.report.render.noise_line import noise_line
from bench_matrix.report.render.plots import Plot
from bench_matrix.report.render.sections import Block, section_blocks
from bench_matrix.report.render.text import (
    HEADLINE_NOTE,
    NO_REASON,
    accuracy_line,
    baseline_note,
    best_text,
    by_reason,
    caption,
    headline_text,
    model_line,
    run_line,
    skip_reason,
)
from bench_matrix.report.render.verdict_view import (HEADERS, INTRO, NUMERIC, closest_lines, open_lines,
                                                     requirement_lines, rows)

TITLE = "bench-matrix report"


def write_html(report: Report, plots: Mapping[str, Sequence[Plot]], path: Path) -> Path:
    """Write the whole report (with `plots`, by model name, inlined) to `path` as one file; return `path`."""
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(page(report, plots), encoding="utf-8", newline="\n")
    return path


def page(report: Report, plots: Mapping[str, Sequence[Plot]]) -> str:
    """The HTML document: byte-identical for a given report and plot files."""
    sections = [_model_section(k, m, plots.get(m.name, ())) for k, m in enumerate(report.models)]
    body = [f"<h1>{TITLE}</h1>", f'<p class="meta">{esc(run_line(report))}</p>', *_verdict(report),
            "<h2>Models</h2>",
            _overview(report), f"<p>Speed-up = baseline p50 ÷ fastest cell p50, both at batch 1. "
            f"{esc(HEADLINE_NOTE)}</p>", *sections,
            "<h2>Environment (all cells)</h2>", _environment(report.environment)]
    return ("<!DOCTYPE html>\n<html lang=\"en\">\n<head>\n<meta charset=\"utf-8\">\n"
            "<meta name=\"viewport\" content=\"width=device-width, initial-scale=1\">\n"
            f"<title>{TITLE}</title>\n<style>{STYLE}</style>\n</head>\n<body>\n"
            + "\n".join(body) + f"\n<script>{SCRIPT}</script>\n</body>\n</html>\n")


def _verdict(report: Report) -> list[str]:
    """The Verdict section: requirements, the recommended cells, the closest where none passes, the answers
    left open, and how noisy the machine was."""
    lines = "".join(f"<li>{esc(line)}</li>" for line in requirement_lines(report.models))
    parts = ["<h2>Verdict</h2>", f"<p>{esc(INTRO)}</p>", f"<ul>{lines}</ul>"]
    if found := rows(report.models):
        parts.append(table(list(HEADERS), NUMERIC, found))
    closest = closest_lines(report.models)
    parts += [f'<p class="note bad"><strong>{esc(line)}</strong></p>' for line in closest]
    parts += [f'<p class="note"><strong>Open:</strong> {esc(line)}</p>' for line in open_lines(report.models)]
    found = noise(report)
    return parts + ([f'<p class="meta noise">{esc(noise_line(found, str))}</p>'] if found is not None else [])


def _anchor(index: int) -> str:
    return f"model-{index + 1}"


def _overview(report: Report) -> str:
    headers = [("Model", "model name: links to its section"), ("Framework", "the model's framework"),
               ("ok", "cells with a result"), ("skipped", "cells that could not run here"),
               ("failed", "cells that raised an error"), ("Fastest cell", "the ok cell with the lowest p50"),
               ("p50 ms", "median latency of the fastest cell at batch 1"),
               ("Speed-up", "baseline p50 ÷ fastest cell p50"), ("Accuracy", HEADLINE_NOTE)]
    rows = []
    for k, model in enumerate(report.models):
        method, latency, speedup = best_text(model)
        rows.append([Html(f'<a href="#{_anchor(k)}">{esc(model.name)}</a>'), model.framework,
                     str(len(model.rows)), str(len(model.skipped)), str(len(model.failed)), method, latency,
                     speedup, headline_text(model)])
    numeric = [False, False, True, True, True, False, True, True, False]
    return table(headers, numeric, rows)


def block_parts(block: Block) -> list[str]:
    """A section's block: its heading, intro, table (when it has items; notes on hover), its lines."""
    heading = f"h{block.level + 1}"
    parts = [f"<{heading}>{esc(block.title)}</{heading}>", f"<p>{esc(block.intro)}</p>"]
    if block.items:
        parts.append(table([(c.header, c.note) for c in block.columns], [c.numeric for c in block.columns],
                           [[c.render(item) for c in block.columns] for item in block.items]))
    return parts + [f"<p>{esc(line)}</p>" for line in block.lines]


def _model_section(index: int, model: ModelSummary, plots: Sequence[Plot]) -> str:
    parts = [f'<section id="{_anchor(index)}">', f"<h2>{esc(model.name)}</h2>",
             f'<p class="meta">{esc(model_line(model, str))}</p>', f"<p>{esc(accuracy_line(model))}</p>",
             *_notes(model), "<h3>Results</h3>", _results(model)]
    if plots:
        parts += ["<h3>Plots</h3>", *(plot_html(plot) for plot in plots)]
    parts += [*(part for block in section_blocks(model) for part in block_parts(block)), *_skipped(model),
              *_failed(model),
              f"<details><summary>Environment of {esc(model.name)}</summary>{_environment(model.environment)}"
              "</details>", "</section>"]
    return "\n".join(parts)


def _notes(model: ModelSummary) -> list[str]:
    """The baseline note, suspect and implausible cells, and cells whose timing was disturbed or too wide."""
    note = baseline_note(model)
    found = [f'<p class="note"><strong>Note:</strong> {esc(note)}</p>'] if note else []
    found += [f'<p class="note bad"><strong>Suspect:</strong> {esc(line)}</p>' for line in model.suspects]
    found += [f'<p class="note bad"><strong>Implausible:</strong> {esc(line)}</p>'
              for line in model.implausible_lines]
    found += [f'<p class="note"><strong>Disturbed (~):</strong> {esc(line)}</p>' for line in model.disturbed]
    found += [f'<p class="note"><strong>Wide (~):</strong> {esc(line)}</p>' for line in model.wide]
    return found


def _results(model: ModelSummary) -> str:
    """The results table (the Markdown page's columns) with its caption and the column notes."""
    if not model.rows:
        return "<p>No cell of this model produced a result.</p>"
    columns = shown(model_columns(model), model.rows)
    headers = [(c.header.replace("\n", " "), c.note) for c in columns]
    rows = [[c.render(row) for c in columns] for row in model.rows]
    classes = ["baseline" if row.is_baseline else "" for row in model.rows]
    notes = "".join(f"<dt>{esc(label)}</dt><dd>{esc(note)}</dd>" for label, note in headers)
    return (f"<p>{esc(caption(model))} Click a column header to sort by it; click again to reverse.</p>"
            + table(headers, [c.numeric for c in columns], rows, classes)
            + f'<details><summary>Columns</summary><dl class="columns">{notes}</dl></details>')


def _skipped(model: ModelSummary) -> list[str]:
    """One box per distinct skip reason: the reason once, then the cells it applies to."""
    if not model.skipped:
        return []
    groups = by_reason(model.skipped, skip_reason)
    parts = [f"<h3>Skipped ({len(model.skipped)})</h3>",
             f"<p>{len(model.skipped)} cell(s) could not run here, for {len(groups)} distinct reason(s).</p>"]
    for group in groups:
        cells = "".join(f"<li>{esc(name)}</li>" for name in cell_names(model, group.records))
        parts.append(f'<div class="group skipped"><pre class="reason">{esc(group.reason)}</pre>'
                     f'<p>{len(group.records)} cell(s):</p><ul class="cells">{cells}</ul></div>')
    return parts


def _failed(model: ModelSummary) -> list[str]:
    """One box per distinct error headline; each cell's full reason (traceback included) folded under it."""
    if not model.failed:
        return []
    groups = by_reason(model.failed, lambda record: headline(record.reason))
    parts = [f"<h3>Failed ({len(model.failed)})</h3>"]
    for group in groups:
        names = cell_names(model, group.records)
        cells = "".join(f"<li><details><summary>{esc(name)}</summary><pre>{esc(record.reason or NO_REASON)}"
                        "</pre></details></li>" for name, record in zip(names, group.records))
        parts.append(f'<div class="group failed"><p class="reason"><strong>{esc(group.reason)}</strong></p>'
                     f'<p>{len(group.records)} cell(s):</p><ul>{cells}</ul></div>')
    return parts


def _environment(env: Environment) -> str:
    """The environment as a label/value table, with a warning when the cells' environments differ."""
    rows = [(label, " / ".join(values)) for label, values in env.fields]
    if env.libraries:
        libraries = (f"{name} {' / '.join(versions)}" for name, versions in env.libraries)
        rows.append(("Libraries", ", ".join(libraries)))
    rows += [(label, " / ".join(values)) for label, values in env.runtime]
    if not rows:
        return "<p>no environment stored with these cells</p>"
    cells = "".join(f'<tr><th scope="row">{esc(label)}</th><td>{esc(value)}</td></tr>'
                    for label, value in rows)
    warnings = "".join(f"<li>{esc(w)}</li>" for w in env.warnings)
    warned = (f'<div class="note"><strong>Warning:</strong> {esc(DIFFERENT_ENVIRONMENTS)}'
              f"<ul>{warnings}</ul></div>")
    return f'<table class="environment">{cells}</table>' + (warned if env.warnings else "")

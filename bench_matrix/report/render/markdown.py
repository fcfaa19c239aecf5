"""GitHub-flavoured Markdown pages of a report: index.md and one page per model, byte-identical for a given store."""

from __future__ import annotations

import hashlib
import html
import os
import re
from collections.abc import Mapping, Sequence
from pathlib import Path
from urllib.parse import quote

from bench_matrix.report.analysis.noise import noise
from bench_matrix.report.analysis.summary import Environment, ModelSummary, Report, headline
from bench_matrix.report.render.columns import (DASH, DIFFERENT_ENVIRONMENTS, Column, cell_names,
                                                model_columns, shown)
from bench_matrix.report.render.noise_line import noise_line
from bench_matrix.report.render.plots import Plot
from bench_matrix.report.render.sections import Block, section_blocks
from bench_matrix.report.render.text import (
    HEADLINE_NOTE,
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
from bench_matrix.store import CellRecord

_COLUMN_NOTES = ("Latency is measured one sample at a time after warm-up runs; p50/p90/p99 are percentiles "
                 "over the timed runs.")


def page_name(model: str) -> str:
    """File name of a model's page; a model called "index" must not overwrite the index, and a name that is not
    a plain file name ("a b/c") gets its safe characters and a short hash of the whole name."""
    if model.lower() == "index":
        return "index-model.md"
    if re.fullmatch(r"[A-Za-z0-9_+-][A-Za-z0-9_.+-]*", model):
        return f"{model}.md"
    safe = re.sub(r"[^A-Za-z0-9_.+-]+", "_", model).strip("._")[:60]
    return f"{safe}-{hashlib.sha256(model.encode()).hexdigest()[:8]}.md"


def write_pages(report: Report, out_dir: Path, plots: Mapping[str, Sequence[Plot]]) -> list[Path]:
    """Write index.md and every model page (embedding its `plots`, by model name) into `out_dir`; return their
    paths, index first."""
    out_dir.mkdir(parents=True, exist_ok=True)
    pages = {"index.md": index_page(report)}
    pages.update({page_name(m.name): model_page(m, plots.get(m.name, ()), out_dir) for m in report.models})
    paths = []
    for name, text in pages.items():
        path = out_dir / name
        path.write_text(text, encoding="utf-8", newline="\n")
        paths.append(path)
    return paths


def index_page(report: Report) -> str:
    """Run summary, the verdict, how noisy the machine was, one line per model (fastest cell, its task's
    accuracy, link) and the environment."""
    found = noise(report)
    lines = ["# bench-matrix report", "", run_line(report), "", *verdict(report.models, INTRO),
             *([_escape_text(noise_line(found, _code)), ""] if found is not None else []), "## Models", "",
             _table(["Model", "Framework", "ok", "skipped", "failed", "Fastest cell", "p50 ms", "Speed-up",
                     "Accuracy"], [False, False, True, True, True, False, True, True, False],
                    [_index_row(m) for m in report.models]),
             "", f"Speed-up = baseline p50 ÷ fastest cell p50, both at batch 1. {HEADLINE_NOTE}",
             "", "## Environment", "", *_environment(report.environment)]
    return "\n".join(lines) + "\n"


def _index_row(model: ModelSummary) -> list[str]:
    method, latency, speedup = best_text(model)
    return [f"[{_escape(model.name)}]({page_name(model.name)})", model.framework, str(len(model.rows)),
            str(len(model.skipped)), str(len(model.failed)), _escape(method), latency, speedup,
            _escape(headline_text(model))]


def model_page(model: ModelSummary, plots: Sequence[Plot], out_dir: Path) -> str:
    """The model's results table with column notes, its plots (paths relative to `out_dir`), each
    scenario's section, skipped cells grouped by reason, failed cells, and the environment."""
    lines = [f"# {_escape(model.name)}", "", "[← all models](index.md)", "",
             _escape_text(model_line(model, _code)), "", _escape(accuracy_line(model)), "",
             *verdict([model])]
    note = baseline_note(model)
    if note:
        lines += [f"> **Note:** {note}", ""]
    lines += [line for suspect in model.suspects for line in (f"> **Suspect:** {_escape_text(suspect)}", "")]
    lines += [line for cell in model.implausible_lines
              for line in (f"> **Implausible:** {_escape_text(cell)}", "")]
    lines += [line for cell in model.disturbed for line in (f"> **Disturbed (~):** {_escape(cell)}", "")]
    lines += [line for cell in model.wide for line in (f"> **Wide (~):** {_escape(cell)}", "")]
    lines += ["## Results", ""]
    if model.rows:
        columns = shown(model_columns(model), model.rows)
        lines += [caption(model), "",
                  _table([_header(c) for c in columns], [c.numeric for c in columns],
                         [[_escape(c.render(row)) for c in columns] for row in model.rows]),
                  "", "Columns:", "", *(f"- **{_header(c)}**: {c.note}" for c in columns),
                  "", f"{_COLUMN_NOTES} {DASH} means the metric was not recorded for that cell.", ""]
    else:
        lines += ["No cell of this model produced a result.", ""]
    lines += _plots(plots, out_dir)
    lines += [line for block in section_blocks(model) for line in block_lines(block)]
    lines += _skipped(model)
    if model.failed:
        lines += [f"## Failed ({len(model.failed)})", ""]
        for record in model.failed:
            lines += _failure(record)
    lines += ["## Environment", "", *_environment(model.environment)]
    return "\n".join(lines) + "\n"


def verdict(models: Sequence[ModelSummary], intro: str = "") -> list[str]:
    """The "Verdict" section: requirements, the recommended cells, the closest where none passes, and the
    answers left open."""
    lines = ["## Verdict", "", *([_escape(intro), ""] if intro else [])]
    lines += [f"- {_escape_text(line)}" for line in requirement_lines(models)] + [""]
    if found := rows(models):
        lines += [_table([h for h, _ in HEADERS], NUMERIC, [[_escape(c) for c in row] for row in found]), ""]
    lines += [line for text in closest_lines(models) for line in (f"> **{_escape(text)}**", "")]
    return lines + [line for text in open_lines(models) for line in (f"> **Open:** {_escape(text)}", "")]


def _plots(plots: Sequence[Plot], out_dir: Path) -> list[str]:
    """The "Plots" section: each plot's title as a heading over the image, linked relative to the page."""
    lines = ["## Plots", ""] if plots else []
    for plot in plots:
        link = quote(Path(os.path.relpath(plot.path, out_dir)).as_posix())
        lines += [f"### {_escape(plot.title)}", "", f"![{_escape(plot.alt)}]({link})", ""]
    return lines


def _skipped(model: ModelSummary) -> list[str]:
    """The "Skipped" section: one row per distinct reason with the number of cells and their labels."""
    if not model.skipped:
        return []
    groups = by_reason(model.skipped, skip_reason)
    rows = [[_reason_cell(group.reason), str(len(group.records)),
             _escape(", ".join(cell_names(model, group.records)))] for group in groups]
    return [f"## Skipped ({len(model.skipped)})", "",
            f"{len(model.skipped)} cell(s) could not run here, for {len(groups)} distinct reason(s):", "",
            _table(["Reason", "Cells", "Methods"], [False, True, False], rows), ""]


def _failure(record: CellRecord) -> list[str]:
    summary = f"<code>{html.escape(record.cell.key)}</code>: {html.escape(headline(record.reason) or 'no reason')}"
    return [f"<details><summary>{summary}</summary>", "", *_fence(record.reason or "(no reason stored)"),
            "", "</details>", ""]


def _fence(text: str) -> list[str]:
    longest = max((len(run) for run in re.findall(r"`+", text)), default=0)
    fence = "`" * max(3, longest + 1)
    return [f"{fence}text", text.rstrip("\n"), fence]


def _environment(env: Environment) -> list[str]:
    lines = [f"- **{label}**: {_escape(' / '.join(values))}" for label, values in env.fields]
    if env.libraries:
        lines.append("- **Libraries**: " + ", ".join(f"{_escape(name)} {_escape(' / '.join(versions))}"
                                                     for name, versions in env.libraries))
    lines += [f"- **{_escape(label)}**: {_code(' / '.join(values))}" for label, values in env.runtime]
    if not lines:
        lines.append("- no environment stored with these cells")
    if env.warnings:
        lines += ["", f"> **Warning:** {DIFFERENT_ENVIRONMENTS}", ">", *(f"> - {_escape(w)}" for w in env.warnings)]
    return lines


def _header(column: Column) -> str:
    return _escape(column.header.replace("\n", " "))


def _table(headers: list[str], numeric: list[bool], rows: list[list[str]]) -> str:
    align = ["---:" if n else ":---" for n in numeric]
    return "\n".join("| " + " | ".join(cells) + " |" for cells in [headers, align, *rows])


def block_lines(block: Block) -> list[str]:
    """A section's block: its heading, intro, table (when it has items) with its column notes, its lines."""
    lines = [f"{'#' * block.level} {_escape(block.title)}", "", _escape(block.intro), ""]
    if block.items:
        lines += [_table([_header(c) for c in block.columns], [c.numeric for c in block.columns],
                         [[_escape(c.render(item)) for c in block.columns] for item in block.items]),
                  "", "Columns:", "", *(f"- **{_escape(h)}**: {_escape(n)}" for h, n in block.notes()), ""]
    return lines + [f"- {_escape(line)}" for line in block.lines] + ([""] if block.lines else [])


def _reason_cell(reason: str | None) -> str:
    lines = [_escape(line.strip()) for line in (reason or "").strip().splitlines() if line.strip()]
    return "<br>".join(lines) or "(no reason stored)"


def _escape(text: str) -> str:
    """Text safe inside a table cell or line: pipes, HTML, `*`, backquotes and brackets escaped."""
    return re.sub(r"([|*`\\\[\]])", r"\\\1", html.escape(text, quote=False))


def _escape_text(text: str) -> str:
    """Like `_escape` but keeping the inline code spans that `_code` produced."""
    parts = re.split(r"(`[^`]*`)", text)
    return "".join(part if part.startswith("`") else _escape(part) for part in parts)


def _code(text: str) -> str:
    return f"`{text.replace('`', '')}`" if text else DASH

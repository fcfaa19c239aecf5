"""Rich tables of a report for the terminal: per model results, skipped and failed cells, and the environment."""

from __future__ import annotations

from rich.cells import cell_len
from rich.console import Console, Group
from rich.panel import Panel
from rich.table import Table
from rich.text import Text

from bench_matrix.report.analysis.noise import noise
from bench_matrix.report.analysis.summary import Environment, ModelSummary, Report, headline
from bench_matrix.report.render.columns import (
    ACCURACY,
    DIFFERENT_ENVIRONMENTS,
    SIZE,
    SPEED,
    THROUGHPUT,
    Column,
    cell_names,
    model_columns,
    shown,
)
from bench_matrix.report.render.noise_line import noise_line
from bench_matrix.report.render.sections import Block, section_blocks
from bench_matrix.report.render.text import (
    accuracy_line,
    baseline_note,
    best_text,
    by_reason,
    caption,
    model_line,
    run_line,
    skip_reason,
)
from bench_matrix.report.render.verdict_view import (
    HEADERS,
    NONE_PASSES,
    NUMERIC,
    closest_lines,
    open_lines,
    requirement_lines,
    rows,
)
from bench_matrix.store import CellRecord

# Ways to lay out the results columns, tried in order until every table fits the console.
_LAYOUTS = (((SIZE, ACCURACY, SPEED, THROUGHPUT),), ((SIZE, ACCURACY), (SPEED, THROUGHPUT)),
            ((SIZE, ACCURACY), (SPEED,), (THROUGHPUT,)), ((SIZE,), (ACCURACY,), (SPEED,), (THROUGHPUT,)))


def print_report(report: Report, console: Console) -> None:
    """Print the run line, every model's tables and the environment panel."""
    console.print(Text(run_line(report)))
    print_verdict(report.models, console)
    if (found := noise(report)) is not None:
        console.print(Text(noise_line(found, str), style="dim"))
    if len(report.models) > 1:
        console.print(_overview(report))
    for model in report.models:
        _print_model(model, console)
    console.print(environment_panel(report.environment, "Environment (all cells)"))


def print_verdict(models: tuple[ModelSummary, ...], console: Console) -> None:
    """The Verdict section: each model's requirements, the recommended cells, the closest where none
    passes, and the answers left open."""
    console.rule(Text("Verdict", style="bold"))
    for line in requirement_lines(models):
        console.print(Text(line, style="dim"))
    found = rows(models)
    if found:
        table = Table(title="Recommended cell per model and target", title_justify="left")
        for (header, _), numeric in zip(HEADERS, NUMERIC):
            table.add_column(header, justify="right" if numeric else "left", overflow="fold")
        for row in found:
            table.add_row(*row, style="red" if row[2] == NONE_PASSES else None)
        console.print(table)
    for line in closest_lines(models):
        console.print(Text(line, style="red"))
    for line in open_lines(models):
        console.print(Text(f"Open: {line}", style="yellow"))


def _overview(report: Report) -> Table:
    table = Table(title="Models", title_justify="left")
    for header in ("Model", "ok", "skipped", "failed", "Fastest cell", "p50 ms", "Speed-up"):
        table.add_column(header, justify="left" if header in ("Model", "Fastest cell") else "right")
    for model in report.models:
        method, latency, speedup = best_text(model)
        table.add_row(model.name, str(len(model.rows)), str(len(model.skipped)), str(len(model.failed)),
                      method, latency, speedup)
    return table


def _print_model(model: ModelSummary, console: Console) -> None:
    console.rule(Text(model.name, style="bold"))
    console.print(Text(model_line(model, str), style="dim"))
    console.print(Text(accuracy_line(model)))
    note = baseline_note(model)
    if note:
        console.print(Text(note, style="yellow"))
    for suspect in model.suspects:
        console.print(Text(f"Suspect: {suspect}", style="bold red"))
    for line in model.implausible_lines:
        console.print(Text(f"Implausible: {line}", style="bold red"))
    for line in model.disturbed:
        console.print(Text(f"Disturbed (~): {line}", style="yellow"))
    for line in model.wide:
        console.print(Text(f"Wide (~): {line}", style="yellow"))
    if model.rows:
        console.print(*results_tables(model, console))
    for block in section_blocks(model):
        print_block(model, block, console)
    if model.skipped:
        console.print(_skipped_table(model))
    if model.failed:
        console.print(_failed_table(model.failed))


def results_tables(model: ModelSummary, console: Console) -> list[Table]:
    """The model's results as one table, or split by column group into as few tables as fit the console."""
    layout = next((layout for layout in _LAYOUTS if all(_width(model, groups) <= console.width for groups in layout)),
                  _LAYOUTS[-1])
    return [_results_table(model, groups, last=i == len(layout) - 1) for i, groups in enumerate(layout)]


def _columns(groups: tuple[str, ...], model: ModelSummary) -> list[Column]:
    return shown((c for c in model_columns(model) if not c.group or c.group in groups), model.rows)


def _width(model: ModelSummary, groups: tuple[str, ...]) -> int:
    """Width of the table without wrapping: widest cell per column, one space of padding each side, borders."""
    texts = [[*c.header.split("\n"), *(c.render(row) for row in model.rows)] for c in _columns(groups, model)]
    return sum(max(map(cell_len, column)) + 3 for column in texts) + 1


def _results_table(model: ModelSummary, groups: tuple[str, ...], last: bool) -> Table:
    title = f"{model.name}: {'results' if len(groups) == len(_LAYOUTS[0][0]) else ', '.join(groups)}"
    table = Table(title=title, title_justify="left", caption=caption(model) if last else None,
                  caption_justify="left")
    columns = _columns(groups, model)
    for column in columns:
        widest = max(cell_len(column.render(row)) for row in model.rows)
        table.add_column(column.header, justify="right" if column.numeric else "left",
                         min_width=widest if column.numeric else min(widest, 16))
    for row in model.rows:
        table.add_row(*(column.render(row) for column in columns), style="bold" if row.is_baseline else None)
    return table


def _skipped_table(model: ModelSummary) -> Table:
    """One row per distinct skip reason: the reason once, then how many cells it applies to and which."""
    groups = by_reason(model.skipped, skip_reason)
    table = Table(title=f"Skipped ({len(model.skipped)} cells, {len(groups)} distinct reasons)",
                  title_justify="left", title_style="yellow")
    table.add_column("Reason", overflow="fold")
    table.add_column("Cells", justify="right")
    table.add_column("Methods", overflow="fold")
    for group in groups:
        names = ", ".join(cell_names(model, group.records))
        table.add_row(Text(group.reason), str(len(group.records)), Text(names))
    return table


def _failed_table(records: tuple[CellRecord, ...]) -> Table:
    title = f"Failed ({len(records)}): the error (full reason in the Markdown page)"
    table = Table(title=title, title_justify="left", title_style="red")
    table.add_column("Method")
    table.add_column("Reason", overflow="fold")
    for record in records:
        table.add_row(record.cell.label, Text(headline(record.reason) or "(no reason stored)"))
    return table


def environment_panel(env: Environment, title: str) -> Panel:
    """The environment as a label/value grid, with warnings when cells were measured in different environments."""
    grid = Table.grid(padding=(0, 2))
    grid.add_column(style="bold")
    grid.add_column(overflow="fold")
    libraries = ", ".join(f"{name} {' / '.join(versions)}" for name, versions in env.libraries)
    for label, values in (*env.fields, *((("Libraries", (libraries,)),) if libraries else ()), *env.runtime):
        grid.add_row(Text(label), Text(" / ".join(values)))
    if not (env.fields or env.libraries or env.runtime):
        grid.add_row("—", "no environment stored with these cells")
    headline = [Text(f"⚠ {DIFFERENT_ENVIRONMENTS}", style="bold yellow")] if env.warnings else []
    warnings = headline + [Text(f"  • {warning}", style="yellow") for warning in env.warnings]
    return Panel(Group(grid, *warnings), title=title, title_align="left")


def print_block(model: ModelSummary, block: Block, console: Console) -> None:
    """A section's block: its table (`brief`'s columns where given), each column as wide as its widest
    figure, then its lines."""
    shown = block.brief if block.brief is not None else block.columns
    rendered = [[column.render(item) for column in shown] for item in block.items]
    if rendered:
        table = Table(title=f"{model.name}: {block.title}", title_justify="left")
        for k, column in enumerate(shown):
            table.add_column(column.header, justify="right" if column.numeric else "left",
                             min_width=max(cell_len(cells[k]) for cells in rendered))
        for cells in rendered:
            table.add_row(*cells)
        console.print(table)
    for line in block.lines:
        console.print(line, highlight=False, markup=False, soft_wrap=True)

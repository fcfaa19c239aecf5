"""Terminal views of a plan (`bench-matrix plan`) and of the installed backends (`bench-matrix backends`)."""

from __future__ import annotations

from pathlib import Path

from rich.console import Console
from rich.markup import escape
from rich.padding import Padding
from rich.table import Table

from bench_matrix.cell import CellPlan
from bench_matrix.executors.local import probe_here
from bench_matrix.jobs import ProbeJob
from bench_matrix.cell import Ruling, RulingKey
from bench_matrix.measure import env as environment
from bench_matrix.plan import ModelPlan, Plan, defaulted, matrix_line, timed_inputs
from bench_matrix.registry import available, vocabulary
from bench_matrix.registry import scenarios
from bench_matrix.selection import Filters
from bench_matrix.store import ResultStore
from bench_matrix.tensors import OPEN_LENGTH, TensorSpec, axes_text, concrete, open_axes, shape_text
from bench_matrix.workspace import Workspace

STATE_STYLE = {"run": "[green]will run[/]", "stored": "[cyan]stored[/]", "skip": "[yellow]skipped[/]",
               "invalid": "[dim]not valid[/]"}


def show_plan(console: Console, plan: Plan, ws: Workspace, filters: Filters, results: Path | None,
              show_all: bool = False, automatic: bool = False) -> None:
    """Cells that will run, are stored, or are skipped (why); then the combinations that are not valid (why).
    `automatic`: the matrix of a model file."""
    filters.check([p.cell for p in plan.cells])
    results = results or ws.results
    store = ResultStore(results, readonly=True) if results.is_file() else None
    here = {environment.host_name()}
    cells = [p for p in plan.cells if filters.keep(p.cell)]
    table = Table(title=f"cells of {plan.matrix.path}")
    chosen = [s for s in scenarios() if s.name in plan.matrix.scenarios]
    for column in ("model", "backend", "strategy", "precision", "target", "state", "reason",
                   *(s.title for s in chosen)):
        table.add_column(column, overflow="fold")
    counts = {"run": 0, "stored": 0, "skip": 0, "invalid": 0}
    for p in sorted((p for p in cells if p.state != "invalid"), key=lambda p: (p.state, p.cell)):
        stored = p.state == "run" and store is not None and store.is_done(p.cell, p.fingerprint, here)
        state = "stored" if stored else p.state
        counts[state] += 1
        c = p.cell
        table.add_row(c.model, c.backend, c.strategy, c.precision, c.target, STATE_STYLE[state],
                      escape(p.reason or ""), *(_planned(p, s.name) for s in chosen))
    console.print(table)
    invalid = [p for p in cells if p.state == "invalid"]
    counts["invalid"] = len(invalid)
    if invalid:
        console.print(_invalid_table(invalid, show_all))
    console.print(f"{counts['run']} will run, {counts['stored']} already stored, {counts['skip']} will be skipped, "
                  f"{counts['invalid']} not valid, {plan.excluded} removed by exclude")
    for line in _slow(plan, [p for p in cells if p.state == "run"]):
        console.print(line, highlight=False, markup=False, soft_wrap=True)
    show_inputs(console, plan, filters, automatic)
    if store:
        store.close()


def show_inputs(console: Console, plan: Plan, filters: Filters, automatic: bool = False) -> None:
    """A line per chosen model: the shapes its inputs are timed at; on standard error, a warning per input
    whose open axes synthetic data gives the default length. `automatic`: the matrix of `run MODEL_FILE`."""
    chosen = {p.cell.model for p in plan.cells if filters.keep(p.cell)}
    warnings = Console(stderr=True)
    for i, model in enumerate(plan.matrix.models):
        if model.name in chosen:
            planned = plan.models[model.name]
            console.print(f"model {model.name}: {_timed(planned)}", highlight=False, markup=False,
                          soft_wrap=True)
            for spec in defaulted(planned):
                warnings.print("[yellow]warning:[/] " + escape(_open_warning(plan, i, spec, automatic)),
                               highlight=False, soft_wrap=True)


def _timed(planned: ModelPlan) -> str:
    """The shapes the model's inputs are timed at, per sample, and where they come from."""
    timed = timed_inputs(planned)
    if timed is None:
        return "inputs of the shapes the data holds (read when it is prepared)"
    shapes = ", ".join(f"{spec.name} {shape_text(spec.shape)} {spec.dtype}" for spec in timed)
    where = "the data's shapes"
    if planned.dataset.kind == "synthetic":
        where = "synthetic data" + (f"; open axes given {OPEN_LENGTH}" if defaulted(planned) else "")
    return f"timed with {shapes} per sample ({where})"


def _open_warning(plan: Plan, i: int, spec: TensorSpec, automatic: bool) -> str:
    """The input's open axes, the length each got, the shape timed, and how to give the lengths."""
    planned = plan.models[plan.matrix.models[i].name]
    at, how = _lengths_hint(planned, i, spec, automatic)
    where = "" if automatic else f"{plan.matrix.path}:{matrix_line(plan.matrix, at)}: "
    return (f"{where}model {planned.spec.name} ({planned.described}): input '{spec.name}' "
            f"({shape_text(spec.shape)}) {spec.dtype} has open {axes_text(open_axes(spec))} (the batch axis "
            f"is 0), which synthetic data gives the default length {OPEN_LENGTH}: it is timed at "
            f"{shape_text(concrete(spec.shape))} per sample; give the lengths to time with {how} "
            f"(docs/models.md#inputs-with-open-axes)")


def _lengths_hint(planned: ModelPlan, i: int, spec: TensorSpec, automatic: bool) -> tuple[tuple, str]:
    """Where in the matrix the input's lengths go, and what to write: --input for `run MODEL_FILE`, the
    declared input's shape, or the model's inputs (all of them, in order: they replace what the file says)."""
    if automatic:
        return ("models", i), f"--input {spec.name}:{','.join(_lengths(spec))}:{spec.dtype}"
    declared = [s.name for s in planned.spec.inputs]
    if spec.name in declared:
        j = declared.index(spec.name)
        return ("models", i, "inputs", j), f"models[{i}].inputs[{j}].shape: [{', '.join(_lengths(spec))}]"
    listed = ", ".join(f"{{name: {s.name}, shape: [{', '.join(_lengths(s))}], dtype: {s.dtype}}}"
                       for s in planned.inputs or ())
    return ("models", i), f"models[{i}].inputs: [{listed}]"


def _lengths(spec: TensorSpec) -> list[str]:
    """The input's axes, each open one as a placeholder for the length to give."""
    return ["<length>" if d is None else str(d) for d in spec.shape]


def _slow(plan: Plan, running: list[CellPlan]) -> list[str]:
    """A line per backend whose cells that will run take minutes to a first result: how many, and why."""
    counted: dict[str, int] = {}
    for p in running:
        counted[p.cell.backend] = counted.get(p.cell.backend, 0) + 1
    slow = {name: (plan.backends.get(name) or {}).get("slow_start") for name in counted}
    return [f"{counted[name]} {name} cell(s): {why}" for name, why in sorted(slow.items()) if why]


def _planned(p: CellPlan, name: str) -> str:
    """What the cell runs of scenario `name` after its latency, or a dash."""
    return next((s.describe() for s in p.scenarios if s.name == name), "—")


def _invalid_table(invalid: list[CellPlan], show_all: bool) -> Table:
    """Not-valid combinations grouped by backend and reason; unless `show_all`, a backend's unimplemented
    strategy/precision/target combinations are one row (`bench-matrix backends` lists what each supports)."""
    groups: dict[tuple[str, ...], list[CellPlan]] = {}
    for p in invalid:
        c, why = p.cell, p.reason or ""
        if show_all:
            key = (c.backend, c.strategy, c.precision, c.target, why)
        elif why.startswith(f"{c.backend} does not implement "):
            key = (c.backend, "", "", "", "combinations it does not implement (plan --all lists them)")
        else:
            key = (c.backend, "", "", "", why)
        groups.setdefault(key, []).append(p)
    table = Table(title="combinations that are not valid (not run, not stored)")
    columns = ("backend", "strategy", "precision", "target", "why", "cells") if show_all else ("backend", "why", "cells")
    for column in columns:
        table.add_column(column, overflow="fold")
    for key, members in sorted(groups.items()):
        shown = key if show_all else (key[0], key[4])
        table.add_row(*shown[:-1], escape(shown[-1]), str(len(members)))
    return table


def show_backends(console: Console, ws: Workspace) -> None:
    """Every installed backend: its package, what it supports, and per installed target whether this machine
    runs it."""
    entries = available()
    ended = probe_here(ProbeJob(ws, tuple(entries)))
    if not ended.ok:
        console.print(f"[red]probing the backends failed:[/] {escape(ended.error or '')}")
        return
    described, rulings = ended.result.backends, ended.result.rulings
    targets = list(vocabulary().targets)
    for name, entry in entries.items():
        info = described[name]
        console.print(f"[bold]{name}[/]  [dim]{escape(entry.distribution)} · {escape(entry.value)}[/]")
        if entry.replaced:
            console.print(f"  replaces the {name} of {escape(', '.join(entry.replaced))} (its class declares "
                          f"replaces = {name!r})")
        if info.get("error"):
            console.print(f"  [red]cannot be loaded:[/] {escape(info['error'])}\n")
            continue
        console.print(f"  {escape(info['description'])}")
        if info["baseline_for"]:
            console.print(f"  fp32 baseline of {', '.join(info['baseline_for'])} models")
        grid = Table.grid(padding=(0, 2))
        grid.add_column(style="dim")
        grid.add_column(overflow="fold")
        for s in info["supports"]:
            grid.add_row("supports", f"{'/'.join(s['frameworks'])}: {', '.join(s['strategies'])} at "
                                     f"{', '.join(s['precisions'])} on {', '.join(s['targets'])}")
        for target in targets:
            grid.add_row(target, target_status(name, target, rulings))
        grid.add_row("versions", escape(", ".join(f"{k} {v}" for k, v in info["versions"].items()) or "—"))
        console.print(Padding(grid, (0, 0, 1, 2)))


def target_status(backend: str, target: str, rulings: dict[RulingKey, Ruling]) -> str:
    """ready / not supported / the skip reasons, with the precisions they concern."""
    mine = {key[3]: v.skip for key, v in rulings.items() if key[0] == backend and key[4] == target}
    if not mine:
        return "[dim]not supported[/]"
    blocked = {}
    for precision, reason in sorted(mine.items()):
        if reason:
            blocked.setdefault(reason, []).append(precision)
    if not blocked:
        return "[green]ready[/]"
    lines = [f"{'/'.join(ps)}: {escape(reason)}" for reason, ps in blocked.items()]
    ready = [p for p, r in mine.items() if not r]
    return ("[green]ready[/] for " + "/".join(ready) + "; " if ready else "") + "[yellow]" + "\n".join(lines) + "[/]"

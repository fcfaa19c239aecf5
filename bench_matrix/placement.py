"""Where the cells run: each of an executor's machines rules on them from the probe job run there
(`expand.rule`); a cell runs on the machines able to run it, or is skipped with their reasons."""

from __future__ import annotations

from dataclasses import dataclass, replace

from bench_matrix.cell import Cell, CellPlan
from bench_matrix.jobs.results import Probe
from bench_matrix.matrix.expand import rule
from bench_matrix.matrix.spec import Matrix


@dataclass(frozen=True)
class Probed:
    """One machine as the probe job found it: its `Probe`, or why the probe failed; `named` is how reasons
    name the machine, `host` the host that records of cells ruled on there carry (None: this machine's)."""

    named: str
    host: str | None
    probe: Probe | None = None
    failed: str | None = None
    down: bool = False  # it cannot measure: it skips no cell, the cells no machine can run fail there


def place(matrix: Matrix, cells: list[CellPlan], machines: dict[str, Probed]
          ) -> tuple[list[CellPlan], dict[str, list[str]]]:
    """The cells as the machines rule on them (no machines: as planned) and the machines able to run each (by
    key): those whose probe says it runs, else those that cannot measure (it fails there); none: skipped."""
    if not machines:
        return cells, {}
    ruled = {name: _ruled(matrix, cells, m) for name, m in machines.items() if not m.down}
    down = [name for name, m in machines.items() if m.down]
    decided, able = [], {}
    for p in cells:
        if p.state not in ("run", "skip"):
            decided.append(p)
            continue
        rulings = {name: states[p.cell] for name, states in ruled.items()}
        able[p.cell.key] = on = [name for name, (state, _) in rulings.items() if state == "run"] or down
        decided.append(replace(p, state="run", reason=None, ruled_on=machines[min(on)].host) if on else
                       replace(p, state="skip", reason=_reasons(machines, rulings),
                               ruled_on=machines[min(rulings)].host))
    return decided, able


def _ruled(matrix: Matrix, cells: list[CellPlan], machine: Probed) -> dict[Cell, tuple[str, str | None]]:
    """Each cell's state (run, skip, invalid) and why, as the machine's probe rules (skip: it failed)."""
    if machine.probe is None:
        return {p.cell: ("skip", machine.failed) for p in cells}
    expansion = rule(matrix, [p.cell for p in cells], 0, machine.probe.rulings, machine.probe.trainers)
    return {q.cell: (q.state, q.reason) for q in expansion.cells}


def _reasons(machines: dict[str, Probed], rulings: dict[str, tuple[str, str | None]]) -> str:
    """Why no machine can run a cell: each distinct reason, after the machines it concerns."""
    by_reason: dict[str, list[str]] = {}
    for name, (_, reason) in rulings.items():
        by_reason.setdefault(reason or "not valid there", []).append(machines[name].named)
    return "; ".join(f"{', '.join(sorted(set(named)))}: {reason}" for reason, named in by_reason.items())

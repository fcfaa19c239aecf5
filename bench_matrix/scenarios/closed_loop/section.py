"""The matrix's `closed_loop` section, read after schema validation: circuits built and checked, selectors
checked against the matrix, models selected by name that cannot drive refused."""

from __future__ import annotations

from dataclasses import replace
from typing import Any

from bench_matrix.matrix.load import Loading
from bench_matrix.matrix.spec import DatasetSpec, ModelSpec
from bench_matrix.matrix.yamlpos import Located, suggest
from bench_matrix.scenarios.closed_loop.spec import (
    MARGIN_RANGES,
    VEHICLES,
    CircuitSpec,
    ClosedLoopSpec,
    MarginSpec,
    MarginsSpec,
)
from bench_matrix.workload.driving.margins import Knob
from bench_matrix.workload.driving.circuits import BUILTIN_CIRCUITS, user_circuit
from bench_matrix.workload.driving.vehicle import SMALL_ROBOT, Response

AT = ("closed_loop",)


def drive_problem(model: ModelSpec, dataset: DatasetSpec, task: str) -> str | None:
    """Why a model cannot drive in the simulator, or None: it must map the built-in driving camera image to
    regressed [v, w], i.e. be evaluated on `dataset: {builtin: driving}` with task regression."""
    if dataset.kind == "builtin" and dataset.builtin == "driving" and task == "regression":
        return None
    builtin = dataset.kind == "builtin"
    what = f"the builtin {dataset.builtin} dataset" if builtin else f"a {dataset.kind} dataset"
    return (f"model {model.name} cannot drive: closed-loop laps feed it the simulator's camera image (the "
            f"built-in driving dataset's) and take its outputs as [v, w], which needs a model evaluated on "
            f"dataset builtin: driving with task regression; it is evaluated on {what} with task {task}")


def closed_loop(data: dict[str, Any], loading: Loading) -> ClosedLoopSpec:
    """The typed section; every problem is added to `loading.report`."""
    report = loading.report
    circuits = tuple(_circuit(i, entry, report) for i, entry in enumerate(data.get("circuits", ["simple"])))
    names = [c.name for c in circuits]
    for i, name in enumerate(names):
        if names.index(name) != i:
            report.add(AT + ("circuits", i), f"circuit '{name}' is listed twice; names must be unique")
    selection = loading.selection(AT, data)
    for i, chosen in enumerate(selection.cells or ()):
        _refuse_non_drivers(i, dict(chosen.values), loading.models, loading.dataset, report)
    return ClosedLoopSpec(circuits=circuits, modes=tuple(data.get("modes", ClosedLoopSpec.modes)),
                          brain_period_ms=data.get("brain_period_ms", ClosedLoopSpec.brain_period_ms),
                          latency_budget_ms=data.get("latency_budget_ms", ClosedLoopSpec.latency_budget_ms),
                          time_limit_s=data.get("time_limit_s"),
                          off_road_limit_s=data.get("off_road_limit_s", ClosedLoopSpec.off_road_limit_s),
                          vehicle=vehicle(data.get("vehicle", "ideal")),
                          margins=margins(data["margins"], names, loading) if "margins" in data else None,
                          selection=selection)


def margins(data: dict[str, Any], circuits: list[str], loading: Loading) -> MarginsSpec:
    """The margins subsection: its searches, circuits (each one of the section's) and cells."""
    report = loading.report
    return MarginsSpec(searches(data, report), margin_circuits(data, circuits, report),
                       loading.selection(AT + ("margins",), data))


def searches(data: dict[str, Any], report: Located) -> tuple[MarginSpec, ...]:
    """The margins to search, in the order latency, speed, perception; a range shorter than its resolution
    reported."""
    if not set(data) & set(MARGIN_RANGES):
        report.add(AT + ("margins",), f"name at least one margin to search: {', '.join(MARGIN_RANGES)}")
    found = []
    for kind, (start, limit, resolution, _, _) in MARGIN_RANGES.items():
        if kind not in data:
            continue
        given, unit = data[kind], "_ms" if kind == "latency" else ""
        knob = (start, given.get(f"limit{unit}", limit), given.get(f"resolution{unit}", resolution))
        if knob[1] - knob[0] < knob[2]:
            report.add(AT + ("margins", kind), f"the {kind} margin's search from {knob[0]:g} to its limit "
                                               f"{knob[1]:g} must span at least its resolution {knob[2]:g}")
            continue
        found.append(MarginSpec(kind, Knob(*knob), given.get("kind", "mix"), given.get("seed", 0)))
    return tuple(found)


def margin_circuits(data: dict[str, Any], names: list[str], report: Located) -> tuple[str, ...]:
    """The circuits margins are searched on: each must be one of the section's."""
    chosen = tuple(data.get("circuits", ()))
    for i, name in enumerate(chosen):
        if name not in names:
            report.add(AT + ("margins", "circuits", i), f"'{name}' is not one of the section's circuits "
                                                         f"({', '.join(names)}){suggest(name, names)}")
    return chosen


def vehicle(entry: str | dict[str, float]) -> Response:
    """A named response, or small_robot's with what is given (times in ms) instead."""
    if isinstance(entry, str):
        return VEHICLES[entry]
    return replace(SMALL_ROBOT, **{key.replace("_ms", "_s"): value / 1e3 if key.endswith("_ms") else value
                                   for key, value in entry.items()})


def _circuit(i: int, entry: str | dict[str, Any], report: Located) -> CircuitSpec:
    """A built-in name, or a mapping: a built-in name with a time limit, or a user circuit with points."""
    at = AT + ("circuits", i)
    if isinstance(entry, str):
        return CircuitSpec(entry)
    name, points = entry["name"], tuple(tuple(p) for p in entry.get("points", ()))
    spec = CircuitSpec(name, points, entry.get("lane_width", CircuitSpec.lane_width),
                       entry.get("time_limit_s"))
    if not points:
        if name not in BUILTIN_CIRCUITS:
            report.add(at + ("name",), f"'{name}' is not a built-in circuit (built-in: "
                                       f"{', '.join(BUILTIN_CIRCUITS)}); a circuit of your own needs 'points'"
                                       f"{suggest(name, list(BUILTIN_CIRCUITS))}")
        elif "lane_width" in entry:
            report.add(at + ("lane_width",), f"'lane_width' is for a circuit given as points; the built-in "
                                             f"circuit {name} has its own")
        return spec
    if name in BUILTIN_CIRCUITS:
        report.add(at + ("name",), f"'{name}' is a built-in circuit's name; give your circuit another name")
    try:
        user_circuit(points, spec.lane_width)
    except ValueError as problem:
        report.add(at + ("points",), f"circuit {name}: {problem}")
    return spec


def _refuse_non_drivers(i: int, fixed: dict[str, str], models: tuple[ModelSpec, ...], shared: DatasetSpec,
                        report: Located) -> None:
    """A selector naming a model that cannot drive asks for the impossible: say so (a selector naming no model
    leaves such models' cells skipped with the reason)."""
    for model in models:
        if model.name == fixed.get("model"):
            dataset = model.dataset or shared
            if problem := drive_problem(model, dataset, model.task or dataset.task):
                report.add(AT + ("cells", i, "model"), problem)

"""Resolve a matrix once, in the parent, into a typed plan: every cell decided (run, skip, invalid, why), its
steps, trainer, baseline, log, fingerprint and
scenarios; every model's task, inputs and baseline; mistakes found before anything runs are a MatrixError
(exit 2)."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any

from bench_matrix import __version__, data
from bench_matrix.cell import Cell, CellPlan, Planned
from bench_matrix.errors import MatrixError
from bench_matrix.images import layout_note
from bench_matrix.jobs import ProbeJob
from bench_matrix.jobs.results import Probe
from bench_matrix.matrix.expand import combinations, rule, training_key, ruling_key
from bench_matrix.matrix.spec import DatasetSpec, Matrix, ModelSpec
from bench_matrix.matrix.yamlpos import Located
from bench_matrix.measure import env as environment
from bench_matrix.registry import available
from bench_matrix.registry import scenarios
from bench_matrix.sources.code import model_code
from bench_matrix.sources.forward_call import call_problem
from bench_matrix.sources.model_io import batch_problem
from bench_matrix.tensors import TensorSpec, binding_problem, concrete, fed, open_axes
from bench_matrix.workspace import Workspace, digest, file_sha256, tree_sha256


Prober = Callable[[ProbeJob], Probe]  # runs the probe job on this machine (executors.local.probe)


@dataclass(frozen=True)
class ModelPlan:
    """A model decided once: dataset, task, inputs (declared or from its file; None: the dataset's), fp32
    reference cell, preparation log, dataset arrays already in per-sample input shape (passed as is)."""

    spec: ModelSpec
    dataset: DatasetSpec
    task: str
    inputs: tuple[TensorSpec, ...] | None
    baseline: Cell | None
    log: Path
    described: str  # how reports name its source: builtin, file or factory + weights, relative to the matrix
    as_is: tuple[str, ...] = ()


@dataclass(frozen=True)
class Plan:
    """Every cell and model of a matrix, decided, plus what the probe learned about each backend."""

    matrix: Matrix
    cells: tuple[CellPlan, ...]
    models: dict[str, ModelPlan]
    excluded: int
    backends: dict[str, Any] = field(default_factory=dict)

    def by_state(self, state: str) -> list[CellPlan]:
        return [p for p in self.cells if p.state == state]


def resolve(matrix: Matrix, workspace: Workspace, prober: Prober) -> Plan:
    """Expand the matrix and rule on every combination with the probe job, which `prober` runs in a child
    process on this machine (imports stay out of the parent)."""
    installed = list(available())
    cells, excluded = combinations(matrix, installed)
    probe = _probe(matrix, cells, installed, workspace, prober)
    baselines = probe.baselines()
    expansion = rule(matrix, cells, excluded, probe.rulings, probe.trainers, baselines)
    models = {m.name: _model_plan(matrix, m, probe.inputs, baselines, workspace) for m in matrix.models}
    _check_models(matrix, models, probe)
    prints = Fingerprints(matrix, probe.backends)
    planned = (replace(p, log=workspace.cell_log(p.cell.key), scenarios=scenarios_of(matrix, p.cell))
               for p in expansion.cells)
    decided = tuple(replace(p, fingerprint=prints.cell(p)) for p in planned)
    return Plan(matrix, decided, models, excluded, probe.backends)


def _probe(matrix: Matrix, cells: list[Cell], installed: list[str], workspace: Workspace,
           prober: Prober) -> Probe:
    """The probe of the cells' combinations and fine-tunings, the model files' inputs and the parameters of
    several-input factories' forward."""
    job = probe_job(matrix, cells, workspace)
    files = tuple(sorted({(m.framework, m.source_format, str(m.file)) for m in matrix.models
                          if m.file is not None and (not m.inputs or m.source_format == "onnx")}))  # batch
    names = tuple(sorted(set(installed) | set(job.backends)))
    factories = tuple(sorted({(m.factory, tuple(map(str, m.python_path))) for m in matrix.models
                              if m.factory and _several_inputs(matrix, m)}))
    return prober(replace(job, backends=names, model_files=files, factories=factories))


def probe_job(matrix: Matrix, cells: list[Cell], workspace: Workspace) -> ProbeJob:
    """The probe job ruling on the cells' combinations and fine-tunings (alone: on an executor's machine)."""
    keys = tuple(sorted({ruling_key(matrix, c) for c in cells}))
    training = tuple(sorted({k for c in cells if (k := training_key(matrix, c))}))
    return ProbeJob(workspace, tuple(sorted({k[0] for k in keys})), keys, training)


def scenarios_of(matrix: Matrix, cell: Cell) -> tuple[Planned, ...]:
    """The scenarios the matrix's sections select for the cell, in matrix order."""
    sections = matrix.scenarios
    chosen = (s.plan(sections[s.name], matrix, cell) for s in scenarios() if s.name in sections)
    return tuple(p for p in chosen if p is not None)


def _model_plan(matrix: Matrix, model: ModelSpec, read: dict[str, tuple[TensorSpec, ...] | None],
                baselines: dict[str, str], workspace: Workspace) -> ModelPlan:
    found = read.get(str(model.file)) if model.file is not None else None
    inputs = model.inputs or found or None
    backend = baselines.get(model.framework)
    baseline = Cell(model.name, model.framework, backend, "none", "fp32", "cpu") if backend else None
    dataset = replace(matrix.dataset_of(model), task=matrix.task_of(model))  # the task decides the labels
    return ModelPlan(model, dataset, dataset.task, inputs, baseline, workspace.log(f"model-{model.name}"),
                     _described(matrix, model), data.model_shaped(dataset, inputs, model.layout))


def timed_inputs(planned: ModelPlan) -> tuple[TensorSpec, ...] | None:
    """The model's inputs as timed: the data's per-sample shapes, or for synthetic data the inputs' own with
    each open axis given OPEN_LENGTH; None where only preparing the data tells (folders of recordings)."""
    if planned.dataset.kind == "synthetic":
        return tuple(replace(spec, shape=concrete(spec.shape)) for spec in planned.inputs or ())
    described = data.describe(planned.dataset, planned.spec.layout, planned.as_is)
    return None if described is None else fed(described, planned.inputs or ())


def defaulted(planned: ModelPlan) -> tuple[TensorSpec, ...]:
    """The model's inputs with an open axis that synthetic data gives the default length (OPEN_LENGTH)."""
    if planned.dataset.kind != "synthetic":
        return ()
    return tuple(spec for spec in planned.inputs or () if open_axes(spec))


def _described(matrix: Matrix, model: ModelSpec) -> str:
    if model.builtin:
        return f"builtin {model.builtin} (trained on the dataset's training split)"
    shown = relative(matrix, model.file or model.weights)
    return shown if model.file else f"{model.factory} + {shown}"


def relative(matrix: Matrix, path: Path) -> str:
    """A path as seen from the matrix file's folder (absolute when it lies elsewhere)."""
    base = matrix.path.parent.resolve()
    return str(path.relative_to(base)) if path.is_relative_to(base) else str(path)


def _several_inputs(matrix: Matrix, model: ModelSpec) -> bool:
    """Whether the model has several inputs: declared, or the dataset's arrays."""
    return len(model.inputs or data.describe(matrix.dataset_of(model), model.layout) or ()) > 1


def _check_models(matrix: Matrix, models: dict[str, ModelPlan], probe: Probe) -> None:
    """Inputs the data cannot feed or a factory's forward cannot take, synthetic data for undeclared inputs,
    an .npz dataset preparing would refuse, a batch size fixed in the model's file: exit 2, located."""
    found = (_model_problem(matrix, i, models[m.name], probe) for i, m in enumerate(matrix.models))
    problems = list(dict.fromkeys(problem for problem in found if problem))  # a shared dataset's: once
    if problems:
        report = Located(matrix.path, matrix.lines)
        raise MatrixError([report.located(at, message) for at, message in problems])


def _model_problem(matrix: Matrix, i: int, planned: ModelPlan, probe: Probe) -> tuple[tuple, str] | None:
    """Where in the matrix and why model `i` cannot run, or None."""
    m, at = planned.spec, ("models", i)
    if planned.dataset.kind == "synthetic" and planned.inputs is None:
        return at, (f"model {m.name}: synthetic data is drawn for the model's inputs, which its "
                    f"{'file does' if m.file else 'factory and weights do'} not declare; declare "
                    f"them under models[{i}].inputs (name, shape, dtype)")
    if unreadable := data.read_problem(planned.dataset, planned.as_is):
        return (at + ("dataset",) if m.dataset else ("dataset",)), unreadable
    described = data.describe(planned.dataset, m.layout, planned.as_is)
    names = [spec.name for spec in planned.inputs] if planned.inputs else list(described or ())
    problem = _forward_problem(m, names, probe)
    if planned.inputs is not None and described is not None and (
            unfit := binding_problem(described, planned.inputs)):
        problem = unfit + layout_note(data.images_read(planned.dataset, planned.as_is), m.layout)
    if problem:
        culprits = f"model {m.name} ({planned.described}){_with_data(matrix, planned.dataset)}"
        return at + ("inputs",) if m.inputs else at, f"{culprits}: {problem}"
    fixed = probe.batches.get(str(m.file)) if m.file else None
    if fixed and (problem := batch_problem(relative(matrix, m.file), m.source_format, fixed,
                                           matrix.settings.batch_size)):
        return at, f"model {m.name}: {problem}"
    return None


def _with_data(matrix: Matrix, dataset: DatasetSpec) -> str:
    """' with data.npz': the data's files as seen from the matrix's folder; '' for built-in or synthetic
    data."""
    return f" with {', '.join(relative(matrix, path) for path in dataset.paths)}" if dataset.paths else ""


def _forward_problem(model: ModelSpec, names: list[str], probe: Probe) -> str | None:
    """Why the factory's forward (its parameters as the probe read them) cannot take these inputs, or None."""
    params = probe.forwards.get(model.factory or "")
    if not params or not names:
        return None
    return call_problem(model.factory or "", params, names, bool(model.inputs))


def matrix_line(matrix: Matrix, at: tuple) -> int:
    """The matrix file's line of the key at `at` (or of the nearest key holding it)."""
    while at and at not in matrix.lines:
        at = at[:-1]
    return matrix.lines.get(at, 1)


class Fingerprints:
    """Everything that determines a cell's result, hashed without where the files lie: a stored record with
    another fingerprint is stale."""

    def __init__(self, matrix: Matrix, backends: dict[str, Any]):
        self.matrix, self.backends = matrix, backends
        self.libraries = environment.library_versions()  # an upgraded runtime makes stored results stale
        self._hashes: dict[Path, str] = {}

    def cell(self, planned: CellPlan) -> str:
        m, cell = self.matrix, planned.cell
        model = m.model(cell.model)
        return digest({"cell": cell.key, "model": self.model(model), "dataset": self.dataset(m.dataset_of(model)),
                       "task": m.task_of(model), "libraries": self.libraries,
                       "backend": self.backends.get(cell.backend, {}).get("versions"),
                       "options": m.backend_options.get(cell.backend, {}),
                       "strategy": m.strategies[cell.strategy].to_dict(),
                       "settings": {k: v for k, v in m.settings.to_dict().items()
                                    if k != "timeout_s"},  # it does not change what is measured
                       "metrics": list(m.metrics), "version": __version__,
                       **{s.name: s.fingerprint() for s in planned.scenarios}})

    def model(self, model: ModelSpec) -> dict[str, Any]:
        portable = asdict(model)
        portable.update(file=None, weights=None, dataset=None,
                        python_path=[relative(self.matrix, p) for p in model.python_path],
                        files=[self._hash(p) for p in (model.file, model.weights) if p is not None],
                        code=model_code(model))
        return portable

    def dataset(self, spec: DatasetSpec) -> dict[str, Any]:
        portable = {**asdict(spec), "paths": [p.name for p in spec.paths]}
        return {"spec": portable, "content": [self._hash(p) for p in spec.paths]}

    def _hash(self, path: Path) -> str:
        """A file's (or folder's) content hash, computed once per run."""
        if path not in self._hashes:
            self._hashes[path] = tree_sha256([path]) if path.is_dir() else file_sha256(path)
        return self._hashes[path]

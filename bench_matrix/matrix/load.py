"""Load a matrix file: safe YAML, schema validation with located did-you-mean messages, typed result."""

from __future__ import annotations

import stat
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

from bench_matrix.errors import MatrixError
from bench_matrix.matrix import load_data, paths
from bench_matrix.matrix.schema import (
    BUILTIN_FRAMEWORKS,
    BUILTIN_MODELS,
    CELL_KEYS,
    FRAMEWORKS,
    STRATEGY_KINDS,
)
from bench_matrix.matrix.extended import axis_values, installed_schema
from bench_matrix.matrix.require import declared
from bench_matrix.matrix.retired import current
from bench_matrix.matrix.spec import (DEFAULT_LAYOUT, MODEL_SUFFIXES, DatasetSpec, Matrix, ModelSpec,
                                      Selection, Selector, Settings, TrainingSpec, file_kind)
from bench_matrix.matrix.validate import StrictValidator, describe
from bench_matrix.matrix.yamlpos import Located, load_with_lines, suggest
from bench_matrix.registry import scenarios
from bench_matrix.strategy import StrategySpec
from bench_matrix.workspace import not_regular

if TYPE_CHECKING:
    from bench_matrix.registry import Vocabulary

__all__ = ["load_matrix", "selector", "suggest"]


@dataclass(frozen=True)
class Loading:
    """What a scenario's section may check itself against while the matrix loads."""

    models: tuple[ModelSpec, ...]
    dataset: DatasetSpec
    known: dict[str, list[str] | None]  # cell key -> its known values (None: any)
    report: Located

    def selection(self, at: tuple, data: dict[str, Any]) -> Selection:
        """A section's `cells` ('all' or partial cells) and `exclude`, at key path `at`, each checked."""
        cells = data.get("cells", "all")
        chosen = None if cells == "all" else tuple(selector(at + ("cells", i), s, self.known, self.report)
                                                   for i, s in enumerate(cells))
        return Selection(chosen, tuple(selector(at + ("exclude", i), s, self.known, self.report)
                                       for i, s in enumerate(data.get("exclude", []))))


def load_matrix(path: str | Path, backends: list[str] | None = None) -> Matrix:
    """Read and validate a matrix; `backends` (installed names) checks the backend axis too. The targets, and
    the precisions and options beyond the built-in ones, are those the installed backends' classes declare."""
    path = Path(path)
    data, lines = load_with_lines(path)
    report = Located(path, lines)
    if not isinstance(data, dict):
        raise MatrixError([f"{path}:1: the top level must be a mapping with 'models', 'dataset' and 'axes'"])
    from bench_matrix.registry import vocabulary as installed

    vocabulary = installed()
    errors = sorted(StrictValidator(installed_schema(vocabulary)).iter_errors(data),
                    key=lambda e: list(map(str, e.absolute_path)))
    mistyped = {tuple(e.absolute_path) for e in errors if e.validator == "type"}
    for error in errors:  # a value of the wrong type gets one message, not also its bounds
        if error.validator == "type" or tuple(error.absolute_path) not in mistyped:
            describe(error, report)
    if report.problems:
        raise MatrixError(report.problems)
    matrix = _build(path, data, lines, report, backends, vocabulary)
    if report.problems:
        raise MatrixError(report.problems)
    return matrix


def _path(base: Path, text: str, at: tuple, report: Located) -> Path | None:
    """The absolute path `text` names (relative: to the matrix's folder); None, reported, when it cannot."""
    path, problem = paths.resolve(base, text)
    if problem:
        report.add(at, problem)
    return path


def _build(path: Path, data: dict[str, Any], lines: dict, report: Located, backends: list[str] | None,
           vocabulary: Vocabulary) -> Matrix:
    base = path.parent.resolve()
    dataset = load_data.dataset(base, data["dataset"], ("dataset",), report)
    models = tuple(_model(base, i, m, dataset, report) for i, m in enumerate(data["models"]))
    names = [m.name for m in models]
    for i, name in enumerate(names):
        if names.index(name) != i:
            report.add(("models", i, "name"), f"model name '{name}' is used twice; names must be unique")
    strategies = _strategies(data.get("strategies", {}), report)
    axes = {key: tuple(values) for key, values in data["axes"].items()}
    for i, name in enumerate(axes["strategy"]):
        if name not in strategies:
            report.add(("axes", "strategy", i), f"unknown strategy '{name}'; allowed: {', '.join(strategies)} "
                                                f"(or declare it under 'strategies'){suggest(name, list(strategies))}")
    if backends is not None:
        for i, name in enumerate(axes.get("backend", ())):
            if name not in backends:
                report.add(("axes", "backend", i), f"no backend '{name}' is installed; installed: "
                                                   f"{', '.join(backends)}{suggest(name, backends)}")
    known = {"model": names, "strategy": list(strategies), "backend": backends, "framework": list(FRAMEWORKS),
             **axis_values(vocabulary)}
    selectors = {}
    for section in ("include", "exclude"):
        selectors[section] = tuple(selector((section, i), s, known, report)
                                   for i, s in enumerate(data.get(section, [])))
    _check_metrics(data.get("metrics", []), report)
    loading = Loading(models, dataset, known, report)
    sections = {s.name: s.read(data[s.name], loading) for s in scenarios() if s.name in data}
    options = {name: dict(given) for name, given in data.get("backend_options", {}).items()}
    settings = current(data.get("settings", {}), report)
    return Matrix(path=path, name=data.get("name", path.stem), models=models, dataset=dataset,
                  strategies=strategies, axes=axes, include=selectors["include"],
                  exclude=selectors["exclude"], settings=Settings(**settings),
                  backend_options=options, metrics=tuple(data.get("metrics", ())), scenarios=sections,
                  requirements=declared(data, report), lines=lines, warnings=tuple(report.warnings))


def _check_metrics(names: list[str], report: Located) -> None:
    """Each listed metric plugin is installed (entry points only: nothing is imported)."""
    if not names:
        return
    from bench_matrix.measure.metric_plugins import metric_names

    installed = metric_names()
    for i, name in enumerate(names):
        if name not in installed:
            report.add(("metrics", i), f"no metric plugin '{name}' is installed; installed: "
                                       f"{', '.join(installed) or 'none'}{suggest(name, installed)}")


def _model(base: Path, i: int, m: dict[str, Any], shared: DatasetSpec, report: Located) -> ModelSpec:
    at = ("models", i)
    file = _path(base, m["file"], at + ("file",), report) if "file" in m else None
    weights = _path(base, m["weights"], at + ("weights",), report) if "weights" in m else None
    framework = m["framework"]
    if "builtin" in m and framework not in BUILTIN_FRAMEWORKS:
        report.add(at + ("framework",), f"built-in models {', '.join(BUILTIN_MODELS)} exist for "
                                        f"{' and '.join(BUILTIN_FRAMEWORKS)}, not {framework}")
    if file is not None:
        _model_file(file, framework, at, report)
    if "factory" in m:
        if "weights" not in m:
            report.add(at, "'factory' needs 'weights' (a state_dict file saved with torch.save)")
        elif weights is not None and (problem := paths.file_problem(weights, "weights file")):
            report.add(at + ("weights",), problem)
        if framework != "pytorch":
            report.add(at + ("framework",), "'factory' builds a pytorch module; set framework: pytorch")
    elif "weights" in m:
        report.add(at + ("weights",), "'weights' only goes with 'factory'")
    own = load_data.dataset(base, m["dataset"], at + ("dataset",), report) if "dataset" in m else None
    inputs = load_data.inputs(m.get("inputs", []), at + ("inputs",), report)
    _model_data(m, at, own or shared, inputs, report)
    layout = m.get("layout", DEFAULT_LAYOUT.get(framework, "nchw"))
    return ModelSpec(name=m["name"], framework=framework, builtin=m.get("builtin"), file=file,
                     factory=m.get("factory"), weights=weights,
                     python_path=_python_path(base, at, m.get("python_path", []), report), layout=layout,
                     training=TrainingSpec(**m.get("training", {})), inputs=inputs, task=m.get("task"),
                     dataset=own)


def _model_data(m: dict[str, Any], at: tuple, data: DatasetSpec, inputs: tuple, report: Located) -> None:
    """The model's task, declared inputs and source fit the data it is evaluated on."""
    if "task" in m and (problem := load_data.task_problem(m["task"], data)):
        report.add(at + ("task",), problem)
    if "builtin" in m and "inputs" in m:
        report.add(at + ("inputs",), "'inputs' is for file and factory models; a built-in model's input is "
                                     "known")
    elif problem := load_data.one_input_problem(data, inputs):
        report.add(at + ("inputs",), problem)
    if data.kind == "synthetic" and "builtin" in m:
        report.add(at + ("builtin",), "a built-in model is trained on its dataset's labels, and synthetic "
                                      "data has none; give it a dataset with labels (a model may have its "
                                      "own 'dataset')")
    elif data.kind == "synthetic" and "factory" in m and not inputs:
        report.add(at, "a factory model on synthetic data must declare 'inputs' (name, shape and dtype of "
                       "each): nothing else says what to generate")


def _python_path(base: Path, at: tuple, entries: list[str], report: Located) -> tuple[Path, ...]:
    """Each entry an existing folder (a missing one would make the factory's import fail obscurely)."""
    folders = []
    for j, text in enumerate(entries):
        folder = _path(base, text, at + ("python_path", j), report)
        if folder is None:
            continue
        folders.append(folder)
        if problem := paths.dir_problem(folder, "python_path folder"):
            report.add(at + ("python_path", j),
                       f"{problem} (python_path lists folders to import 'factory' from)")
    return tuple(folders)


def _model_file(file: Path, framework: str, at: tuple, report: Located) -> None:
    """A model file must be a regular file with a known ending, or a SavedModel directory of regular files."""
    found, problem = paths.mode(file)
    if problem:
        report.add(at + ("file",), problem)
        return
    if found is None:
        report.add(at + ("file",), f"model file not found: {file}")
    elif stat.S_ISDIR(found):
        if not (file / "saved_model.pb").is_file():
            report.add(at + ("file",), f"'{file}' is a directory without saved_model.pb: a model directory "
                                       f"must be a TensorFlow SavedModel")
            return
        if problem := paths.saved_model_problem(file):
            report.add(at + ("file",), problem)
    elif kind := not_regular(found):
        report.add(at + ("file",), f"'{file}' is {kind}, not a model file; give a regular file")
        return
    expected = file_kind(file)
    if expected is None:
        report.add(at + ("file",), f"unsupported model file '{file.name}'; allowed: files ending "
                                   f"{', '.join(MODEL_SUFFIXES)} (TorchScript, torch.export, ONNX, Keras) "
                                   f"or a SavedModel directory")
    elif expected[0] != framework:
        report.add(at + ("framework",), f"'{file.name}' is a {expected[0]} model file, but framework "
                                        f"is '{framework}'")


def _strategies(declared: dict[str, Any], report: Located) -> dict[str, StrategySpec]:
    out = {kind: StrategySpec(name=kind, kind=kind) for kind in STRATEGY_KINDS}
    pending = dict(declared)
    for name, entry in declared.items():
        if "kind" in entry:
            if name in STRATEGY_KINDS and entry["kind"] != name:
                report.add(("strategies", name), f"'{name}' is a built-in strategy kind; give your variant "
                                                 f"another name or keep kind: {name}")
            options = {k: v for k, v in entry.items() if k not in ("kind", "description")}
            out[name] = StrategySpec(name=name, kind=entry["kind"], options=options)
            pending.pop(name)
    for name, entry in pending.items():
        steps = []
        for i, step in enumerate(entry["steps"]):
            if step not in out:
                report.add(("strategies", name, "steps", i), f"unknown strategy '{step}'; steps must name built-in "
                                                             f"or earlier-declared strategies{suggest(step, list(out))}")
            else:
                steps.append(out[step])
        stages = [STRATEGY_KINDS[s.kind]["stage"] for s in steps if s.kind]
        if "conversion" in stages and stages.index("conversion") != len(stages) - 1:
            report.add(("strategies", name, "steps"), "only the last step may be a post-training "
                                                      "(conversion) strategy; training steps come first")
        out[name] = StrategySpec(name=name, kind=None, steps=tuple(steps))
    return out


def selector(at: tuple, entry: dict[str, str], known: dict[str, list[str] | None],
             report: Located) -> Selector:
    """A partial cell at key path `at`; each value must be known (`known`: per key, None for any)."""
    for key, value in entry.items():
        allowed = known.get(key)
        if allowed is not None and value not in allowed:
            report.add(at + (key,), f"'{value}' is not a known {key}; known: {', '.join(allowed)}"
                                    f"{suggest(value, allowed)}")
    return Selector(values=tuple((k, entry[k]) for k in CELL_KEYS if k in entry))

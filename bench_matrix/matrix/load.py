"""Load a matrix file: safe YAML, schema validation with located did-you-mean messages, typed result."""

from __future__ import annotations

import difflib
import math
import stat
from pathlib import Path
from typing import Any

import jsonschema

from bench_matrix.errors import MatrixError
from bench_matrix.matrix import paths
from bench_matrix.matrix.schema import BUILTIN_FRAMEWORKS, BUILTIN_MODELS, CELL_KEYS, FRAMEWORKS, PRECISIONS, SCHEMA, STRATEGY_KINDS, TARGETS
from bench_matrix.matrix.spec import (
    DEFAULT_LAYOUT,
    MODEL_SUFFIXES,
    DatasetSpec,
    LabelSpec,
    Matrix,
    ModelSpec,
    Preprocess,
    Selector,
    Settings,
    SplitSpec,
    StrategySpec,
    TrainingSpec,
    file_kind,
)
from bench_matrix.matrix.yamlpos import format_path, load_with_lines
from bench_matrix.workspace import not_regular

DRIVING_LABELS = LabelSpec(columns=("v", "w"), offset=(6.5, -7.1), scale=(17.5, 14.2))


def _is_integer(_checker: Any, value: Any) -> bool:
    return isinstance(value, int) and not isinstance(value, bool)  # 2.0 and True are not counts


def _is_number(_checker: Any, value: Any) -> bool:
    return _is_integer(_checker, value) or (isinstance(value, float) and math.isfinite(value))


StrictValidator = jsonschema.validators.extend(
    jsonschema.Draft202012Validator,
    type_checker=jsonschema.Draft202012Validator.TYPE_CHECKER.redefine_many(
        {"integer": _is_integer, "number": _is_number}))


def suggest(word: str, allowed: list[str] | tuple[str, ...]) -> str:
    """'; did you mean X?' when a close match exists."""
    close = difflib.get_close_matches(str(word), [str(a) for a in allowed], n=1, cutoff=0.6)
    return f"; did you mean '{close[0]}'?" if close else ""


class _Located:
    """Collects problems as 'file:line: key: message'."""

    def __init__(self, path: Path, lines: dict[tuple, int]):
        self.path, self.lines, self.problems = path, lines, []

    def add(self, at: tuple, message: str) -> None:
        probe = at
        while probe not in self.lines and probe:
            probe = probe[:-1]
        self.problems.append(f"{self.path}:{self.lines.get(probe, 1)}: {format_path(at)}: {message}")


def load_matrix(path: str | Path, backends: list[str] | None = None) -> Matrix:
    """Read and validate a matrix; `backends` (installed names) checks the backend axis too."""
    path = Path(path)
    data, lines = load_with_lines(path)
    report = _Located(path, lines)
    if not isinstance(data, dict):
        raise MatrixError([f"{path}:1: the top level must be a mapping with 'models', 'dataset' and 'axes'"])
    errors = sorted(StrictValidator(SCHEMA).iter_errors(data), key=lambda e: list(map(str, e.absolute_path)))
    mistyped = {tuple(e.absolute_path) for e in errors if e.validator == "type"}
    for error in errors:  # a value of the wrong type gets one message, not also its bounds
        if error.validator == "type" or tuple(error.absolute_path) not in mistyped:
            _describe(error, report)
    if report.problems:
        raise MatrixError(report.problems)
    matrix = _build(path, data, lines, report, backends)
    if report.problems:
        raise MatrixError(report.problems)
    return matrix


def _describe(error: jsonschema.ValidationError, report: _Located) -> None:
    at = tuple(error.absolute_path)
    schema, value, kind = error.schema, error.instance, error.validator
    if kind == "additionalProperties" and isinstance(value, dict):
        allowed = sorted(schema.get("properties", {}))
        for key in [k for k in value if k not in schema.get("properties", {})]:
            hint = f"allowed: {', '.join(allowed)}" if allowed else "no keys are allowed here"
            report.add(at + (key,), f"unknown key '{key}'; {hint}{suggest(key, allowed)}")
    elif kind in ("enum", "const"):
        allowed = schema.get("enum", [schema.get("const")])
        report.add(at, f"'{value}' is not allowed; allowed: {', '.join(map(str, allowed))}{suggest(value, allowed)}")
    elif kind == "required":
        report.add(at, f"missing required key {error.message.split(' is a required')[0]}")
    elif kind == "type":
        report.add(at, _type_message(error.validator_value, value))
    elif kind == "oneOf" and (unknown := _hidden_unknown_keys(schema, value)):
        for key in unknown:
            allowed = ", ".join(sorted(schema["properties"]))
            report.add(at + (key,), f"unknown key '{key}'; allowed: {allowed} (and the options of the kind)"
                                    f"{suggest(key, sorted(_known_keys(schema)))}")
    elif kind in ("oneOf", "pattern") and "x-message" in schema:
        report.add(at, schema["x-message"] + (f" (got {value!r})" if kind == "pattern" else ""))
    elif kind in ("minimum", "exclusiveMinimum", "maximum", "exclusiveMaximum"):
        sign = {"minimum": ">=", "exclusiveMinimum": ">", "maximum": "<=", "exclusiveMaximum": "<"}[kind]
        report.add(at, f"must be {sign} {error.validator_value}, got {value!r}")
    elif kind in ("minItems", "maxItems", "minProperties"):
        report.add(at, error.message.replace("[]", "the list").replace("{}", "the mapping"))
    elif kind == "uniqueItems":
        report.add(at, f"lists a value twice: {value!r}")
    else:
        report.add(at, error.message)


def _type_message(expected: str | list[str], value: Any) -> str:
    names = expected if isinstance(expected, str) else " or ".join(expected)
    got = f"got {type(value).__name__} {value!r}"
    if isinstance(value, float) and not math.isfinite(value):
        return f"expected a finite {names}, {got} (.nan and .inf are not allowed)"
    if isinstance(value, float) and value.is_integer() and "integer" in expected:
        return f"expected {names}, {got}; write it without a decimal point"
    return f"expected {names}, {got}"


def _known_keys(schema: dict[str, Any]) -> set[str]:
    """Keys an object schema allows in any of its conditional branches (allOf: if/then)."""
    branches = [b.get("then", {}).get("properties", {}) for b in schema.get("allOf", [])]
    return set(schema.get("properties", {})).union(*branches)


def _hidden_unknown_keys(schema: dict[str, Any], value: Any) -> list[str]:
    """Unknown keys no other error reports: an object schema, without additionalProperties, failed oneOf."""
    if not isinstance(value, dict) or "additionalProperties" in schema or "properties" not in schema:
        return []
    known = _known_keys(schema)
    return [key for key in value if key not in known]


def _path(base: Path, text: str, at: tuple, report: _Located) -> Path | None:
    """The absolute path `text` names (relative: to the matrix's folder); None, reported, when it cannot."""
    path, problem = paths.resolve(base, text)
    if problem:
        report.add(at, problem)
    return path


def _build(path: Path, data: dict[str, Any], lines: dict, report: _Located, backends: list[str] | None) -> Matrix:
    base = path.parent.resolve()
    models = tuple(_model(base, i, m, report) for i, m in enumerate(data["models"]))
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
             "precision": list(PRECISIONS), "target": list(TARGETS)}
    selectors = {}
    for section in ("include", "exclude"):
        selectors[section] = tuple(_selector(section, i, s, known, report) for i, s in enumerate(data.get(section, [])))
    return Matrix(path=path, name=data.get("name", path.stem), models=models,
                  dataset=_dataset(base, data["dataset"], report), strategies=strategies, axes=axes,
                  include=selectors["include"], exclude=selectors["exclude"],
                  settings=Settings(**data.get("settings", {})), lines=lines)


def _model(base: Path, i: int, m: dict[str, Any], report: _Located) -> ModelSpec:
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
    layout = m.get("layout", DEFAULT_LAYOUT.get(framework, "nchw"))
    return ModelSpec(name=m["name"], framework=framework, builtin=m.get("builtin"), file=file,
                     factory=m.get("factory"), weights=weights,
                     python_path=_python_path(base, at, m.get("python_path", []), report), layout=layout,
                     training=TrainingSpec(**m.get("training", {})))


def _python_path(base: Path, at: tuple, entries: list[str], report: _Located) -> tuple[Path, ...]:
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


def _model_file(file: Path, framework: str, at: tuple, report: _Located) -> None:
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


def _dataset(base: Path, d: dict[str, Any], report: _Located) -> DatasetSpec:
    at = ("dataset",)
    kind = next(k for k in ("builtin", "npz", "folder") if k in d)
    located = _data_paths(base, kind, d, report)
    if kind != "builtin":
        for key in ("samples", "circuits"):
            if key in d:
                report.add(at + (key,), f"'{key}' only applies to the builtin dataset")
    samples, circuits = d.get("samples", DatasetSpec.samples), d.get("circuits", DatasetSpec.circuits)
    if kind == "builtin" and circuits > samples:
        report.add(at + ("circuits",), f"{circuits} circuits for {samples} samples: every circuit needs at "
                                       f"least one sample; lower circuits or raise samples")
    pre = d.get("preprocess", {})
    crop = pre.get("crop")
    labels = d.get("labels", {})
    default_labels = DRIVING_LABELS if kind == "builtin" else LabelSpec(offset=None, scale=None)
    label_spec = LabelSpec(columns=tuple(labels.get("columns", default_labels.columns)),
                           offset=_tuple(labels.get("offset", default_labels.offset)),
                           scale=_tuple(labels.get("scale", default_labels.scale)))
    for key in ("offset", "scale"):
        value = getattr(label_spec, key)
        if value is not None and kind != "npz" and len(value) not in (1, len(label_spec.columns)):
            report.add(at + ("labels", key), f"has {len(value)} values for {len(label_spec.columns)} label columns")
    split = d.get("split", {})
    fractions = {k: split.get(k, getattr(SplitSpec, k)) for k in ("train", "calibration", "test")}
    if abs(sum(fractions.values()) - 1.0) > 1e-6:
        report.add(at + ("split",), f"train + calibration + test must add up to 1, got "
                                    f"{' + '.join(f'{v:g}' for v in fractions.values())} = {sum(fractions.values()):g}")
    mean, std = _tuple(pre.get("mean")), _tuple(pre.get("std"))
    if (mean is None) != (std is None):
        report.add(at + ("preprocess",), "give both 'mean' and 'std', or neither")
    for start, end in (("top", "bottom"), ("left", "right")):
        if crop and crop.get(start) is not None and crop.get(end) is not None and crop[end] <= crop[start]:
            report.add(at + ("preprocess", "crop", end), f"{end} ({crop[end]}) must be greater than {start} "
                                                         f"({crop[start]}): the bounds are slice bounds, "
                                                         f"image[top:bottom, left:right]")
    return DatasetSpec(
        kind=kind, paths=located, samples=samples, circuits=circuits, seed=d.get("seed", DatasetSpec.seed),
        preprocess=Preprocess(crop=(crop.get("top"), crop.get("bottom"), crop.get("left"), crop.get("right"))
                              if crop else None,
                              resize=_tuple(pre.get("resize")), scale=pre.get("scale", 1.0 / 255.0), mean=mean, std=std),
        labels=label_spec,
        split=SplitSpec(**fractions, by=split.get("by", "auto")))


def _data_paths(base: Path, kind: str, d: dict[str, Any], report: _Located) -> tuple[Path, ...]:
    """The npz file or the folders, each checked: a regular .npz file; folders holding a regular data.csv."""
    if kind == "builtin":
        return ()
    listed = isinstance(d[kind], list)
    located = []
    for j, text in enumerate(d[kind] if listed else [d[kind]]):
        at = ("dataset", kind) + ((j,) if listed else ())
        path = _path(base, text, at, report)
        if path is None:
            continue
        located.append(path)
        if kind == "npz":
            problem = paths.file_problem(path, "dataset file")
        else:
            problem = paths.dir_problem(path, "dataset folder") or _csv_problem(path / "data.csv")
        if problem:
            report.add(at, problem)
    return tuple(located)


def _csv_problem(csv: Path) -> str | None:
    if paths.mode(csv) == (None, None):
        return f"{csv.parent} has no data.csv (expected header image_name,v,w,...)"
    return paths.file_problem(csv, "data.csv file")


def _tuple(value: Any) -> tuple | None:
    return tuple(value) if value is not None else None


def _strategies(declared: dict[str, Any], report: _Located) -> dict[str, StrategySpec]:
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


def _selector(section: str, i: int, entry: dict[str, str], known: dict[str, list[str] | None],
              report: _Located) -> Selector:
    for key, value in entry.items():
        allowed = known.get(key)
        if allowed is not None and value not in allowed:
            report.add((section, i, key), f"'{value}' is not a known {key}; known: {', '.join(allowed)}"
                                          f"{suggest(value, allowed)}")
    return Selector(values=tuple((k, entry[k]) for k in CELL_KEYS if k in entry))

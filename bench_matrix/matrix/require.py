"""Requirements as a matrix declares them (checked while it loads, or read alone from its file when a report
is made) and as `--require KEY=VALUE` gives them; every problem located like the matrix's others."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

import yaml

from bench_matrix.errors import MatrixError, UserError
from bench_matrix.matrix.requirements import BOUND_KEYS, Declared, Requirements, bound_problem
from bench_matrix.matrix.validate import StrictValidator, describe
from bench_matrix.matrix.yamlpos import Located, load_with_lines
from bench_matrix.registry import scenarios


def declared(data: dict[str, Any], report: Located) -> Declared:
    """The top level's requirements and each model's own, from schema-valid data. Problems: a bound whose min
    exceeds its max, a scenario's keys without its section, a plugin figure of a plugin not in `metrics`."""
    found = {(): data.get("requirements") or {}}
    found.update({("models", i): m.get("requirements") or {} for i, m in enumerate(data.get("models", ()))})
    plugins = data.get("metrics") or []
    for at, given in found.items():
        for key, problem in bound_problem(given):
            report.add(at + ("requirements", key), problem)
        for name in [s.name for s in scenarios() if s.name in given and s.name not in data]:
            report.add(at + ("requirements", name), f"this matrix has no '{name}' section, so no cell has "
                                                    f"these figures; add the section or drop these "
                                                    f"requirements")
        for key in [k for k in given if "." in k and k.split(".")[0] not in plugins]:
            plugin = key.split(".")[0]
            report.add(at + ("requirements", key), f"'{key}' is a figure of metric plugin '{plugin}', which "
                                                   f"this matrix's metrics do not list (metrics: "
                                                   f"{', '.join(plugins) or 'none'})")
    own = {m["name"]: Requirements.from_data(m["requirements"]) for m in data.get("models", ())
           if "requirements" in m}
    return Declared(Requirements.from_data(found[()]), own)


def read_file(path: Path) -> Declared:
    """The requirements of the matrix file at `path`, its other sections unchecked (a report needs only
    these); MatrixError with every problem located."""
    data, lines = load_with_lines(path)
    if not isinstance(data, dict):
        raise MatrixError([f"{path}:1: the top level must be a mapping with 'models', 'dataset' and 'axes'"])
    report = Located(path, lines)
    _validate(data, _file_schema(), report)
    if not report.problems:
        found = declared(data, report)
    if report.problems:
        raise MatrixError(report.problems)
    return found


def parse_require(texts: Sequence[str]) -> dict[str, Any]:
    """`--require KEY=VALUE` options as requirements data (a scenario's key as NAME.KEY, a bound as
    METRIC.min or METRIC.max); UserError naming the option for anything the matrix would refuse."""
    data: dict[str, Any] = {}
    for text in texts:
        key, sep, value = text.partition("=")
        if not sep or not key.strip() or not value.strip():
            raise UserError(f"--require {text!r}: write KEY=VALUE, e.g. --require p50_ms=50, --require "
                            f"max_drop=5%, --require top1.min=0.9")
        _put(data, key.strip(), _value(value.strip()))
    report = Located(Path("--require"), {})
    _validate({"requirements": data}, _file_schema(), report)
    for key, problem in bound_problem(data):
        report.add(("requirements", key), problem)
    if report.problems:
        raise UserError("; ".join(p.replace("--require:1: requirements.", "--require ", 1)
                                  for p in report.problems))
    return data


def _put(data: dict[str, Any], key: str, value: Any) -> None:
    """KEY's value into `data`: a scenario's NAME.KEY and a bound's METRIC.min nested, other keys as given."""
    names = {s.name for s in scenarios()}
    head, _, rest = key.partition(".")
    if head in names and rest:
        data.setdefault(head, {})[rest] = value
    elif key.rpartition(".")[2] in BOUND_KEYS and "." in key:
        figure, _, bound = key.rpartition(".")
        data.setdefault(figure, {})[bound] = value
    else:
        data[key] = value


def _value(text: str) -> Any:
    """A number, or the text (5%, p50) as given."""
    try:
        value = yaml.safe_load(text)
    except yaml.YAMLError:
        return text
    return value if isinstance(value, int | float) and not isinstance(value, bool) else text


def _file_schema() -> dict[str, Any]:
    """What of a matrix file requirements read: the top level's and each model's, and the model names."""
    from bench_matrix.matrix.extended import matrix_schema

    properties = matrix_schema()["properties"]
    own = properties["models"]["items"]["properties"]["requirements"]
    return {"type": "object", "properties": {
        "requirements": properties["requirements"], "metrics": properties["metrics"],
        "models": {"type": "array", "items": {"type": "object", "required": ["name"], "properties": {
            "name": {"type": "string"}, "requirements": own}}}}}


def _validate(data: dict[str, Any], schema: dict[str, Any], report: Located) -> None:
    errors = StrictValidator(schema).iter_errors(data)
    for error in sorted(errors, key=lambda e: list(map(str, e.absolute_path))):
        describe(error, report)

"""The `requirements` a cell must meet to pass (docs/matrix.md, requirements): their schema fragment, their
typed form, and a model's own merged over the matrix's. Selectable scenarios add keys of their own."""

from __future__ import annotations

import copy
import math
import re
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

from bench_matrix.measure.metrics import DIRECTIONS

TIMED = {"p50_ms": "max", "p99_ms": "max", "throughput_sps": "min"}  # timed: judged with their interval
SIZES = {"size_mib": "max", "peak_rss_mib": "max"}
OBJECTIVES = ("p50", "p99", "size", "throughput")
METRICS = tuple(key for key in DIRECTIONS if key != "mse_per_output")  # recorded task metrics with a bound
PLUGIN_FIGURE = r"^[A-Za-z_][\w-]*\.[\w.-]+$"  # a metric plugin's figure, NAME.FIGURE
PERCENT = re.compile(r"^\s*(\d+(\.\d+)?)\s*%\s*$")
BOUND_KEYS = ("min", "max")

_LIMIT = {"type": "number", "exclusiveMinimum": 0, "maximum": 1e12}
_BOUND = {"type": "object", "additionalProperties": False, "minProperties": 1,
          "properties": {"min": {"type": "number"}, "max": {"type": "number"}},
          "description": "{min: X} and/or {max: X}: the figure must be at least X / at most X"}
_DESCRIPTIONS = {"p50_ms": "median latency at batch 1, ms, at most", "p99_ms": "99th percentile, ms, at most",
                 "throughput_sps": "samples per second at the throughput batch, at least",
                 "size_mib": "artifact size, MiB, at most",
                 "peak_rss_mib": "peak resident memory, MiB, at most"}

SCHEMA: dict[str, Any] = {
    "type": "object", "additionalProperties": False,
    "description": "what a cell must meet to pass; a model's own override the matrix's, key by key",
    "properties": {
        "max_drop": {"oneOf": [{"type": "number", "minimum": 0, "maximum": 1e12},
                               {"type": "string", "pattern": PERCENT.pattern}],
                     "x-message": "give the largest loss of the task's headline metric against the fp32 "
                                  "baseline as a percentage of its value ('5%') or as an absolute difference "
                                  "(0.01)",
                     "description": "headline metric (mse, top1, cosine_similarity) against the baseline's"},
        **{key: {**_LIMIT, "description": _DESCRIPTIONS[key]} for key in (*TIMED, *SIZES)},
        **{key: _BOUND for key in METRICS},
        "objective": {"enum": list(OBJECTIVES), "description": "how passing cells are ranked (default p50)"},
    },
    "patternProperties": {PLUGIN_FIGURE: _BOUND},
}


def with_scenarios(fragment: dict[str, Any]) -> dict[str, Any]:
    """The fragment with each selectable scenario's requirement keys, under its name."""
    from bench_matrix.registry import scenarios

    out = copy.deepcopy(fragment)
    for scenario in scenarios():
        if scenario.requirements:
            keys = {key: _scenario_limit(bound, f"{what}, {bound}imum")
                    for key, (bound, what) in scenario.requirements.items()}
            out["properties"][scenario.name] = {"type": "object", "additionalProperties": False,
                                                "minProperties": 1, "properties": keys}
    return out


def _scenario_limit(bound: str, description: str) -> dict[str, Any]:
    """A scenario figure's limit: a number, or {min: X} (or {max: X}) naming the figure's own bound."""
    number = {"type": "number", "minimum": 0, "maximum": 1e12}
    return {"if": {"type": "object"},
            "then": {"type": "object", "additionalProperties": False, "required": [bound],
                     "properties": {bound: number}},
            "else": number, "description": f"{description}: X or {{{bound}: X}}"}


@dataclass(frozen=True)
class Limit:
    """One requirement: `key` as written (a scenario's as "NAME.KEY"), the bound ("max", "min"; "drop" for
    max_drop) and its value; `relative`: max_drop given as a percentage (value is then the fraction)."""

    key: str
    bound: str
    value: float
    relative: bool = False

    def describe(self) -> str:
        """'p50_ms ≤ 25', 'top1 ≥ 0.9', 'max_drop 5 %', 'max_drop 0.01'."""
        if self.bound == "drop":
            return f"max_drop {self.value * 100:g} %" if self.relative else f"max_drop {self.value:g}"
        return f"{self.key} {'≤' if self.bound == 'max' else '≥'} {self.value:g}"


@dataclass(frozen=True)
class Requirements:
    """A model's requirements: typed `limits`, the `objective`, and the data they were read from."""

    limits: tuple[Limit, ...] = ()
    objective: str = "p50"
    data: Mapping[str, Any] = field(default_factory=dict, compare=False)

    @classmethod
    def from_data(cls, data: Mapping[str, Any]) -> Requirements:
        """The typed requirements of schema-valid data."""
        scenarios = _scenario_bounds()
        limits = []
        for key, value in data.items():
            if key == "max_drop":
                limits.append(_drop(value))
            elif key in TIMED or key in SIZES:
                limits.append(Limit(key, {**TIMED, **SIZES}[key], float(value)))
            elif key in scenarios and isinstance(value, Mapping):
                limits += [Limit(f"{key}.{name}", scenarios[key][name],
                                 float(v[scenarios[key][name]] if isinstance(v, Mapping) else v))
                           for name, v in value.items()]
            elif isinstance(value, Mapping):
                limits += [Limit(key, bound, float(value[bound])) for bound in BOUND_KEYS if bound in value]
        return cls(tuple(limits), str(data.get("objective", "p50")), dict(data))

    def over(self, own: Mapping[str, Any] | None) -> Requirements:
        """These requirements with `own` overriding them key by key (a scenario's keys one by one)."""
        return Requirements.from_data(merged(self.data, own or {}))

    def describe(self) -> str:
        """One line: every limit, then the objective."""
        limits = ", ".join(limit.describe() for limit in self.limits) or "none"
        return f"{limits}; objective {self.objective}"


@dataclass(frozen=True)
class Declared:
    """The requirements a matrix declares: the top level's and each model's own, by model name."""

    top: Requirements = field(default_factory=Requirements)
    own: Mapping[str, Requirements] = field(default_factory=dict)

    def of(self, model: str, overrides: Mapping[str, Any] | None = None) -> Requirements:
        """A model's requirements: its own over the top level's, then `overrides` (--require) over both."""
        own = self.own.get(model)
        found = self.top.over(own.data if own else None)
        return found.over(overrides) if overrides else found

    def to_json(self) -> dict[str, Any]:
        return {"requirements": dict(self.top.data), "models": {n: dict(r.data) for n, r in self.own.items()}}

    @classmethod
    def from_json(cls, data: Mapping[str, Any]) -> Declared:
        own = {name: Requirements.from_data(given) for name, given in (data.get("models") or {}).items()}
        return cls(Requirements.from_data(data.get("requirements") or {}), own)


def merged(base: Mapping[str, Any], own: Mapping[str, Any]) -> dict[str, Any]:
    """`own` over `base`, key by key; a scenario's section merged key by key too."""
    names = set(_scenario_bounds())
    out = copy.deepcopy(dict(base))
    for key, value in own.items():
        if key in names and isinstance(out.get(key), Mapping):
            out[key] = {**out[key], **value}
        else:
            out[key] = copy.deepcopy(value)
    return out


def bound_problem(data: Mapping[str, Any]) -> list[tuple[str, str]]:
    """(key, problem) for each {min, max} bound whose min exceeds its max."""
    return [(key, f"min {value['min']:g} is above max {value['max']:g}: no figure can pass")
            for key, value in data.items()
            if isinstance(value, Mapping) and value.get("min", -math.inf) > value.get("max", math.inf)]


def _drop(value: Any) -> Limit:
    if isinstance(value, str):
        return Limit("max_drop", "drop", float(PERCENT.match(value).group(1)) / 100, relative=True)
    return Limit("max_drop", "drop", float(value))


def _scenario_bounds() -> dict[str, dict[str, str]]:
    """Per selectable scenario with requirement keys: key -> "min" or "max"."""
    from bench_matrix.registry import scenarios

    return {s.name: {key: bound for key, (bound, _) in s.requirements.items()} for s in scenarios()
            if s.requirements}

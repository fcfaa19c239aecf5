"""What the kit checks: one case per combination a backend declares and model of its framework, the rules a
case can break, and the tolerance stated for each precision."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Literal

import numpy as np

from bench_matrix.backend import Backend
from bench_matrix.conformance.models import MODELS
from bench_matrix.matrix.schema import STRATEGY_KINDS

CONVERSION_KINDS = ("none", "ptq_dynamic", "ptq_static")  # the strategies a case converts with
# The source formats a backend may be asked about, per framework (`option_reason`, `probe_source`).
SOURCE_FORMATS = {"pytorch": ("state_dict", "torchscript", "torch_export"),
                  "tensorflow": ("keras", "h5", "saved_model", "keras_qat"), "onnx": ("onnx",)}


class RuleBroken(AssertionError):
    """A backend broke a rule of the contract; the message starts with the rule's name."""

    def __init__(self, rule: str, message: str):
        super().__init__(f"rule {rule}: {message}")
        self.rule = rule


@dataclass(frozen=True)
class Tolerance:
    """How far a precision's outputs may be from the fp32 reference: `factor` times the reference's largest
    absolute value (`max_abs`), or times each output column's standard deviation over inputs (`spread`)."""

    factor: float
    basis: Literal["max_abs", "spread"]

    def bound(self, reference: np.ndarray) -> np.ndarray:
        """The largest difference allowed for each element of one sample's output."""
        if self.basis == "spread":
            return self.factor * reference.std(axis=0)
        return np.full(reference.shape[1:], self.factor * float(np.abs(reference).max()))


# fp32: the same arithmetic up to summation order. fp16 (10-bit mantissa) and bf16 (7-bit): rounding through a
# few layers. int8: every quantised tensor is off by up to half a step of its calibrated range; the built-in
# backends land within 0.04-0.23 of a column's spread on the kit's models, while an output that lost its
# input's influence is off by about 2 spreads, and one not dequantised by orders of magnitude.
TOLERANCES = {"fp32": Tolerance(1e-5, "max_abs"), "fp16": Tolerance(1e-2, "max_abs"),
              "bf16": Tolerance(5e-2, "max_abs"), "int8": Tolerance(0.3, "spread")}
REPEAT = TOLERANCES["fp32"]  # how close two loads, or two conversions, must come


@dataclass(frozen=True)
class Case:
    """One combination a backend declares, on one of the kit's models of its framework."""

    backend: str
    framework: str
    strategy: str
    precision: str
    target: str
    model: str

    @property
    def id(self) -> str:
        return "-".join((self.backend, self.framework, self.strategy, self.precision, self.target,
                         self.model))


def cases_of(backend: Backend, models: tuple[str, ...] = MODELS) -> list[Case]:
    """Every declared combination with a conversion strategy, on each of `models`, in declaration order."""
    found: dict[Case, None] = {}
    for s in backend.supports:
        for combo in ((f, st, p, t) for f in s.frameworks for st in s.strategies if st in CONVERSION_KINDS
                      for p in s.precisions for t in s.targets):
            found.update({Case(backend.name, *combo, model): None for model in models})
    return list(found)


def combinations(backend: Backend) -> list[tuple[str, str, str, str]]:
    """Every (framework, strategy, precision, target) the backend declares, conversion or not."""
    return sorted({(f, st, p, t) for s in backend.supports for f in s.frameworks for st in s.strategies
                   for p in s.precisions for t in s.targets})


def option_variants(kind: str) -> list[dict[str, Any]]:
    """No options, then each option of the strategy kind alone at each value it can take (integers: their
    minimum), as a matrix may give them."""
    variants: list[dict[str, Any]] = [{}]
    for name, schema in STRATEGY_KINDS.get(kind, {}).get("options", {}).items():
        values = schema.get("enum") or {"boolean": [True, False], "integer": [schema.get("minimum", 1)]}.get(
            schema.get("type"), [])
        variants += [{name: value} for value in values]
    return variants


def reason_problem(answer: object, call: str) -> str | None:
    """Why `answer` (of `call`) is not a reason (a non-empty str) or None."""
    if answer is None or (isinstance(answer, str) and answer.strip()):
        return None
    return f"{call} returned {answer!r} ({type(answer).__name__}), not a non-empty str or None"

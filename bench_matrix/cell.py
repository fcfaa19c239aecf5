"""A cell: one model through one backend with one strategy, precision and target; what a backend says of a
combination (its ruling, by key) and what the plan decides of a cell."""

from __future__ import annotations

from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, ClassVar, Literal

from bench_matrix.strategy import StrategySpec

PlanState = Literal["run", "skip", "invalid"]
# (backend, framework, conversion kind, precision, target, source format, conversion options as JSON, training
# key as JSON or ""): everything a backend needs to rule on a combination before any model is loaded (after a
# fine-tuning, the format converted is the trainer's output, which the probe substitutes)
RulingKey = tuple[str, str, str, str, str, str, str, str]
# (framework, source format, training steps as JSON, task): what a trainer needs to rule on a fine-tuning
# strategy
TrainingKey = tuple[str, str, str, str]


@dataclass(frozen=True)
class Ruling:
    """A backend's answer for one combination: not valid (why), or valid but not runnable here (why)."""

    invalid: str | None = None
    skip: str | None = None
    by: str | None = None  # for a fine-tuning strategy: the trainer that will apply it
    format: str | None = None  # ... and the format of the model it writes


@dataclass(frozen=True, order=True)
class Cell:
    """The coordinates of one measurement."""

    model: str
    framework: str
    backend: str
    strategy: str
    precision: str
    target: str

    @property
    def key(self) -> str:
        return "/".join((self.model, self.backend, self.strategy, self.precision, self.target))

    def as_dict(self) -> dict[str, str]:
        return asdict(self)

    @property
    def label(self) -> str:
        """Short method name for tables: backend strategy precision [target]."""
        parts = [self.backend, self.strategy, self.precision]
        return " ".join(parts + ([] if self.target == "cpu" else [self.target]))


NO_STEP = StrategySpec(name="none", kind="none")


@dataclass(frozen=True)
class Planned:
    """A scenario decided for one cell, in the parent; the measure job carries it to the artifact's process,
    which runs `function` ('module:function', taking Loaded and this, giving an Outcome)."""

    name: ClassVar[str]  # the scenario's; its record fields are `name` or start with `name_`
    function: ClassVar[str]

    def fingerprint(self) -> dict[str, Any]:
        """What the scenario's fields depend on beyond the cell's own fingerprint."""
        raise NotImplementedError

    def describe(self) -> str:
        """What `bench-matrix plan` shows for the cell under the scenario's column (rich markup)."""
        raise NotImplementedError

    def timed(self) -> bool:
        """Whether its figures depend on the wall clock: then it runs under the machine's timing lock."""
        return False


@dataclass(frozen=True)
class CellPlan:
    """A cell decided once, in the parent: run, skip or reject and why; its backend's conversion step; its
    fine-tuning and by whom; its baseline cell, log, result fingerprint and scenarios after latency."""

    cell: Cell
    state: PlanState
    reason: str | None = None
    step: StrategySpec = NO_STEP  # what the backend is asked to do (conversion kind, or QAT kind), with options
    training: tuple[StrategySpec, ...] = ()  # fine-tuning steps applied first, in order
    trainer: str | None = None  # the trainer that applies them
    baseline: Cell | None = None  # the model's fp32 reference cell
    log: Path | None = field(default=None, compare=False)
    fingerprint: str = ""
    scenarios: tuple[Planned, ...] = ()  # measured after the latency scenario, in order
    ruled_on: str | None = None  # the host that ruled on the cell (a device), when not this machine

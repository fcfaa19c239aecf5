"""The scenario seam: what is measured once a cell's artifact is loaded. The core scenarios (CORE: latency)
run in every measure job, first; the registered ones are selected per cell by their own matrix section."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, ClassVar, Protocol

if TYPE_CHECKING:
    from bench_matrix.backend import Backend, Session
    from bench_matrix.cell import Planned
    from bench_matrix.jobs import MeasureJob
    from bench_matrix.matrix.load import Loading
    from bench_matrix.matrix.spec import Matrix
    from bench_matrix.measure.gpu import GpuMemory
    from bench_matrix.measure.schedule import Window
    from bench_matrix.measurement import Measurement


@dataclass(frozen=True)
class Loaded:
    """A cell's loaded session in its measure job's process, with what loading it learned."""

    job: MeasureJob
    backend: Backend
    session: Session
    load_s: float
    on_gpu: bool
    gpu_memory: GpuMemory | None
    cpus: Any


@dataclass(frozen=True)
class Outcome:
    """What a scenario adds to the cell's record: metrics fields and raw series (stats.pack_samples bytes)."""

    fields: dict[str, Any]
    samples: dict[str, bytes] = field(default_factory=dict)


class Windows(Protocol):
    """The timed windows a scenario serves to the executor's rounds, by kind (docs/metrics.md §5)."""

    @property
    def kinds(self) -> tuple[str, ...]: ...

    def window(self, kind: str, seconds: float) -> Window: ...


class Scenario:
    """A matrix scenario: its section's schema, typed reading, per-cell plan, figures its requirements bound,
    report Section; a CORE one has no section or plan (no fingerprint part) but `timer` and `evaluate`."""

    name: ClassVar[str]  # the matrix section's key, the Planned's name and its record fields' prefix
    title: ClassVar[str]  # the plan view's column
    schema: ClassVar[dict[str, Any]]  # JSON Schema of the section
    # requirement keys it adds under its name in `requirements`: key -> ("min" or "max", what the figure is)
    requirements: ClassVar[dict[str, tuple[str, str]]] = {}
    section: ClassVar[str | None] = None  # "module:NAME" of its report Section (report/render/sections.py)

    def read(self, data: dict[str, Any], loading: Loading) -> Any:
        """The typed section from its schema-valid data; problems go to `loading.report`."""
        raise NotImplementedError

    def plan(self, section: Any, matrix: Matrix, cell: Any) -> Planned | None:
        """The scenario for this cell, or None when the section does not select it."""
        raise NotImplementedError

    def figure(self, key: str, metrics: Measurement) -> float | None:
        """The stored figure requirement `key` bounds, or None when the record has none."""
        return None

    def timer(self, loaded: Loaded) -> Windows | None:
        """A core scenario's windows served to the executor's rounds, warmed up; None when it serves none."""
        return None

    def evaluate(self, loaded: Loaded, before: Outcome | None = None) -> Outcome:
        """A core scenario's fields measured outside the rounds: now, or `before` them brought up to date."""
        return Outcome({})


CORE = ("bench_matrix.scenarios.latency:Latency",)  # 'module:class': every measure job's first scenarios


def fields(name: str, others: dict[str, Any]) -> dict[str, Any]:
    """The record fields of scenario `name` among a measurement's `others`."""
    return {k: v for k, v in others.items() if k == name or k.startswith(f"{name}_")}

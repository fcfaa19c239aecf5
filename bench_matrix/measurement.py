"""A cell's typed measurement and its one serialiser to and from the record's flat `metrics` JSON object
(docs/metrics.md §2): `Measurement.from_json(data).to_json() == data` for today's and older records."""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any, ClassVar

TASKS = ("regression", "classification", "none")  # what a model's outputs are scored as (docs/metrics.md)


def _typed(value: Any) -> Any:
    return tuple(value) if isinstance(value, list) else value


def _plain(value: Any) -> Any:
    return list(value) if isinstance(value, tuple) else value


@dataclass(frozen=True)
class Figures:
    """Typed figures read from JSON keys; `present` keeps which keys were there, in their order (a key
    missing from an older record reads None and is written back missing); an OPEN object keeps the rest."""

    KEYS: ClassVar[dict[str, str]] = {}  # attribute -> JSON key, where they differ
    OPEN: ClassVar[bool] = False  # a JSON object of its own: keys it does not type go to `others`
    present: tuple[str, ...] = field(default=(), repr=False, compare=False)
    others: dict[str, Any] = field(default_factory=dict, repr=False)

    @classmethod
    def names(cls) -> dict[str, str]:
        """JSON key -> attribute, for every typed figure."""
        return {cls.KEYS.get(f.name, f.name): f.name for f in dataclasses.fields(cls)
                if f.name not in ("present", "others")}

    @classmethod
    def from_json(cls, data: Mapping[str, Any]) -> Any:
        """The figures of `data` this class types; other keys are left to the caller."""
        names = cls.names()
        mine = [k for k in data if k in names or cls.OPEN]
        return cls(**{names[k]: _typed(data[k]) for k in mine if k in names}, present=tuple(mine),
                   others={k: data[k] for k in mine if k not in names})

    def to_json(self) -> dict[str, Any]:
        names = self.names()
        return {k: _plain(getattr(self, names[k])) if k in names else self.others[k] for k in self.present}


@dataclass(frozen=True)
class LatencyStats(Figures):
    """One timed series in ms (measure/stats.py:latency_summary): the median's 95 % interval and its width."""

    OPEN: ClassVar[bool] = True

    mean: float | None = None
    p50: float | None = None
    p90: float | None = None
    p99: float | None = None
    std: float | None = None
    min: float | None = None
    n: int | None = None
    p50_ci: tuple[float, ...] | None = None
    p50_ci_rel: float | None = None


@dataclass(frozen=True)
class Interference(Figures):
    """Whether other work disturbed the timing, why, and the limits it was judged by."""

    OPEN: ClassVar[bool] = True

    flagged: bool | None = None
    reason: str | None = None
    limits: dict[str, Any] | None = None
    phases: dict[str, Any] | None = None  # latency, latency_e2e, throughput: every attempt and which was kept


@dataclass(frozen=True)
class Throughput(Figures):
    KEYS: ClassVar[dict[str, str]] = {"sps": "throughput_sps", "batches": "throughput_batches",
                                      "ci": "throughput_ci"}
    sps: float | None = None
    batches: int | None = None
    batch_size: int | None = None
    ci: tuple[float, ...] | None = None  # 95 % interval of the rate, from the rounds


@dataclass(frozen=True)
class Speedup(Figures):
    """Baseline time ÷ cell time, paired by round (measure/rounds.py:speedup), with its 95 % interval."""

    OPEN: ClassVar[bool] = True

    value: float | None = None
    ci: tuple[float, ...] | None = None
    ci_half: float | None = None  # the interval's larger side relative to the value (0.02 = ±2 %)
    rounds: int | None = None


@dataclass(frozen=True)
class RoundsFacts(Figures):
    """How the cell's rounds went: latency rounds kept, why stopped, target, width reached, window length,
    processes, latency windows per process and round (baseline: several), process spread (own and model's)."""

    OPEN: ClassVar[bool] = True

    rounds: int | None = None
    stop: str | None = None
    target: float | None = None
    reached: float | None = None
    window_s: float | None = None
    processes: int | None = None
    visits: float | None = None
    process_spread: float | None = None
    model_spread: float | None = None


@dataclass(frozen=True)
class Size(Figures):
    KEYS: ClassVar[dict[str, str]] = {"bytes": "size_bytes", "gzip_bytes": "size_gzip_bytes"}
    bytes: int | None = None
    gzip_bytes: int | None = None
    files: int | None = None
    params: int | None = None


@dataclass(frozen=True)
class Memory(Figures):
    KEYS: ClassVar[dict[str, str]] = {"gpu_mb": "peak_gpu_mem_mb", "gpu_method": "gpu_mem_method"}
    peak_rss_mb: float | None = None
    gpu_mb: float | None = None
    gpu_method: str | None = None
    gpu_name: str | None = None


@dataclass(frozen=True)
class TaskMetrics(Figures):
    """Accuracy against the labels (regression, classification) and fidelity to the fp32 baseline."""

    KEYS: ClassVar[dict[str, str]] = {"max_abs_diff": "max_abs_diff_vs_baseline",
                                      "cosine": "cosine_similarity"}
    mse: float | None = None
    mae: float | None = None
    mse_per_output: tuple[float, ...] | None = None
    max_abs_diff: float | None = None
    cosine: float | None = None
    snr_db: float | None = None
    top1: float | None = None
    top5: float | None = None
    top1_agreement: float | None = None
    per_output: tuple[Any, ...] | None = None
    test_samples: int | None = None
    outputs_sha256: str | None = None  # of the float32 test-split predictions

    def figure(self, key: str) -> Any:
        """A figure by its record key (HEADLINE and DIRECTIONS name them so), or None."""
        return getattr(self, self.names()[key])


@dataclass(frozen=True)
class Passes(Figures):
    """The latency passes: each pass's p50, failed passes, the kept attempt's stability and attempts."""

    KEYS: ClassVar[dict[str, str]] = {"p50": "latency_passes_p50", "failed": "latency_passes_failed",
                                      "stability": "latency_stability", "attempts": "latency_attempts"}
    p50: tuple[float, ...] | None = None
    failed: int | None = None
    stability: float | None = None
    attempts: int | None = None

    @property
    def made(self) -> int:
        """Passes measured; 1 for records stored before passes were counted."""
        return 1 if self.p50 is None else len(self.p50)


@dataclass(frozen=True)
class Setup(Figures):
    """How the cell was measured: threads, pinned CPUs, the session's report, the timing lock, load time."""

    threads: int | None = None
    cpu_affinity: tuple[int, ...] | None = None
    session: dict[str, Any] | None = None
    timing_window: dict[str, Any] | None = None
    load_s: float | None = None


_NESTED = {"latency_ms": ("latency", LatencyStats), "latency_ms_e2e": ("latency_e2e", LatencyStats),
           "interference": ("interference", Interference), "speedup": ("speedup", Speedup),
           "rounds": ("rounds", RoundsFacts)}
_FLAT = {"throughput": Throughput, "size": Size, "memory": Memory, "task": TaskMetrics, "passes": Passes,
         "setup": Setup}


@dataclass(frozen=True, eq=False)
class Measurement:
    """An ok cell's figures, typed; `others` holds the fields of scenarios (closed_loop_*), metric plugins
    (NAME.FIGURE) and conversion facts. Two are equal when their JSON objects are."""

    latency: LatencyStats | None = None
    latency_e2e: LatencyStats | None = None
    interference: Interference | None = None
    speedup: Speedup | None = None  # absent for the baseline, and for records from before the rounds
    rounds: RoundsFacts | None = None
    throughput: Throughput = Throughput()
    size: Size = Size()
    memory: Memory = Memory()
    task: TaskMetrics = TaskMetrics()
    passes: Passes = Passes()
    setup: Setup = Setup()
    others: dict[str, Any] = field(default_factory=dict)
    order: tuple[str, ...] = field(default=(), repr=False, compare=False)

    @classmethod
    def from_json(cls, data: Mapping[str, Any]) -> Measurement:
        """The measurement of a stored `metrics` object, of this release or an older one."""
        nested = {attr: kind.from_json(data[key]) for key, (attr, kind) in _NESTED.items()
                  if isinstance(data.get(key), dict)}
        flat = {attr: kind.from_json(data) for attr, kind in _FLAT.items()}
        typed = {key for key, (attr, _) in _NESTED.items() if attr in nested}
        typed.update(key for kind in _FLAT.values() for key in kind.names() if key in data)
        others = {k: v for k, v in data.items() if k not in typed}
        return cls(**nested, **flat, others=others, order=tuple(data))

    def to_json(self) -> dict[str, Any]:
        """The flat `metrics` object, its keys in the order they were measured or read."""
        parts = dict(self.others)
        parts.update({key: getattr(self, attr).to_json() for key, (attr, _) in _NESTED.items()
                      if getattr(self, attr) is not None})
        for attr in _FLAT:
            parts.update(getattr(self, attr).to_json())
        return {k: parts[k] for k in (*self.order, *parts) if k in parts}

    def figure(self, key: str) -> Any:
        """A flat figure by its record key (`mse`, `throughput_sps`, a plugin's `NAME.FIGURE`), or None."""
        for attr, kind in _FLAT.items():
            names = kind.names()
            if key in names:
                return getattr(getattr(self, attr), names[key])
        return self.others.get(key)

    def __eq__(self, other: object) -> bool:
        return isinstance(other, Measurement) and self.to_json() == other.to_json()

"""What a backend is: declared capabilities, a probe, convert (source -> artifact) and load (artifact -> session)."""

from __future__ import annotations

import importlib.util
from abc import ABC, abstractmethod
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, ClassVar

import numpy as np

from bench_matrix.op_profile import Profile
from bench_matrix.strategy import StrategySpec
from bench_matrix.sources import SourceModel
from bench_matrix.tensors import Inputs

# Where a target runs: the host's CPU (the default), or an NVIDIA GPU through CUDA, whose cells are also timed
# end to end (host arrays in, outputs fetched), record the GPU's name and memory, and get a GPU share on Ray.
DEVICES = ("cpu", "cuda")


@dataclass(frozen=True)
class Support:
    """One family of combinations a backend runs; a backend declares a tuple of these as data."""

    frameworks: tuple[str, ...]
    strategies: tuple[str, ...]
    precisions: tuple[str, ...]
    targets: tuple[str, ...]
    # modules converting these combinations needs and running them does not (a device that only runs the
    # converted artifact lacks them): judged where the model is converted, never on a device that only runs
    convert_needs: tuple[str, ...] = ()

    def covers(self, framework: str, strategy: str, precision: str, target: str) -> bool:
        return (framework in self.frameworks and strategy in self.strategies
                and precision in self.precisions and target in self.targets)


@dataclass(frozen=True)
class ConvertRequest:
    """Everything a backend needs to turn the pristine source model into an artifact."""

    source: SourceModel  # source.inputs: the model's named inputs (shape per sample, dtype)
    # What the backend is asked to do, resolved once by the planner: a conversion kind (none, ptq_dynamic,
    # ptq_static) or, for a quantisation-aware-trained source with no conversion step, its QAT kind; with its options.
    step: StrategySpec
    precision: str
    target: str
    out_dir: Path  # write every file of the artifact here, and nothing else
    calibration: Callable[[int], Inputs]  # n -> the first n preprocessed calibration samples of every input
    threads: int
    seed: int
    # Files derived from this source alone (e.g. its fp32 export), reusable by every conversion of it with this
    # backend and these library versions; None: nothing is shared.
    shared_dir: Path | None = None
    # The largest batch the cell runs (latency runs batch 1): ahead-of-time engines cover 1..max_batch.
    max_batch: int = 1
    # This backend's own options from the matrix (`backend_options`), validated against Backend.options;
    # whatever `load` needs of them goes into the returned metadata.
    options: dict[str, Any] = field(default_factory=dict)
    # A folder of this conversion's own in the workspace for its temporary files (tempfile's dir=; None: the
    # system's), removed when the conversion ends and, where it was killed, by the next run. A file for
    # shared_dir is written here first and then moved there (shutil.move), never half-written there.
    scratch_dir: Path | None = None


class Session(ABC):
    """A loaded artifact ready to run; `execute` returns only once the work is finished."""

    def prepare(self, inputs: Inputs) -> Any:
        """Put a batch (one array per named input) where the runtime reads it (device memory, a feed dict);
        not timed."""
        return inputs

    @abstractmethod
    def execute(self, prepared: Any) -> Any:
        """Run one batch and wait for completion (synchronise devices); this call is what is timed."""

    def fetch(self, outputs: Any) -> list[np.ndarray]:
        """Every output of the model, in order, as float32 host arrays with the batch axis first (int8 outputs
        dequantised with their scale and zero point)."""
        if isinstance(outputs, (list, tuple)):
            return [np.asarray(o, dtype=np.float32) for o in outputs]
        return [np.asarray(outputs, dtype=np.float32)]

    def predict(self, inputs: Inputs) -> list[np.ndarray]:
        return self.fetch(self.execute(self.prepare(inputs)))

    def info(self) -> dict[str, Any]:
        """Facts about the session worth recording (providers actually used, device, threads)."""
        return {}

    def profile(self, prepared: Any, calls: int) -> Profile:
        """Optional: `prepared` run `calls` times under the runtime's own profiler, after the timed rounds (the
        profile scenario); the default has none, and says so."""
        return Profile(reason="no profiler hook (its Session does not implement profile)")


class Backend(ABC):
    """A runtime that converts models and runs them; knows nothing of the runner."""

    name: ClassVar[str]
    description: ClassVar[str]
    supports: ClassVar[tuple[Support, ...]]
    baseline_for: ClassVar[tuple[str, ...]] = ()  # frameworks whose fp32 reference this backend computes
    # The backend's own options under `backend_options: {name: {...}}` in a matrix, as JSON Schema properties
    # (validated with the matrix; defaults are the backend's to apply). Targets and precisions beyond the
    # built-in ones are declared simply by naming them in `supports`.
    options: ClassVar[dict[str, Any]] = {}
    revision: ClassVar[int] = 1  # raise it when the conversion changes: cached artifacts are then redone
    # why a first result takes minutes (it compiles): the automatic matrix of a model file leaves it out
    slow_start: ClassVar[str] = ""
    devices: ClassVar[dict[str, str]] = {}  # target -> the device it runs on (one of DEVICES); unnamed: cpu
    # the name of a backend another distribution registers (a built-in one) that this one replaces; without
    # it, two registrations of one name are an error naming both
    replaces: ClassVar[str] = ""

    def device(self, target: str) -> str:
        """The device `target` runs on, as `devices` declares it (cpu when it does not name the target)."""
        return self.devices.get(target, "cpu")

    def versions(self) -> dict[str, str]:
        """Versions of the libraries this backend uses (in the artifact cache key and in each record's `env`)."""
        return {}

    def probe(self, target: str, precision: str) -> str | None:
        """Why this machine cannot run `target`/`precision`, or None when it can."""
        return None

    def probe_source(self, framework: str, source_format: str) -> str | None:
        """Why this machine cannot read `framework` models in `source_format` (a converter missing), or None."""
        return None

    def convert_needs_reason(self, framework: str, strategy: str, precision: str, target: str) -> str | None:
        """Why this machine cannot convert the combination: the modules its Supports' convert_needs name that
        cannot be found here (found without importing them), or None. Not asked where only running happens."""
        missing = sorted({m for s in self.supports if s.covers(framework, strategy, precision, target)
                          for m in s.convert_needs if importlib.util.find_spec(m) is None})
        if not missing:
            return None
        return f"needs {', '.join(missing)} to convert {strategy} at {precision}, not installed"

    def invalid_reason(self, framework: str, strategy: str, precision: str, target: str) -> str | None:
        """Why the combination is not one this backend implements, or None."""
        if any(s.covers(framework, strategy, precision, target) for s in self.supports):
            return None
        if not any(framework in s.frameworks for s in self.supports):
            frameworks = sorted({f for s in self.supports for f in s.frameworks})
            return f"{self.name} takes {', '.join(frameworks)} models, not {framework}"
        return f"{self.name} does not implement {strategy} at {precision} on {target}"

    def option_reason(self, step: StrategySpec, source_format: str) -> str | None:
        """Why this backend cannot apply `step` (the resolved conversion step) with its options to a source of
        `source_format`, or None; called once per combination, at plan time."""
        return None

    @abstractmethod
    def convert(self, request: ConvertRequest) -> dict[str, Any]:
        """Write the artifact's files into request.out_dir; return JSON-serialisable metadata for `load`."""

    @abstractmethod
    def load(self, artifact_dir: Path, meta: dict[str, Any], target: str, precision: str,
             threads: int) -> Session:
        """Load a converted artifact for inference with exactly `threads` threads."""

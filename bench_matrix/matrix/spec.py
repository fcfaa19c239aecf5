"""Typed, validated contents of a matrix file."""

from __future__ import annotations

from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

from bench_matrix.matrix.requirements import Declared
from bench_matrix.measurement import TASKS
from bench_matrix.strategy import StrategySpec
from bench_matrix.tensors import TensorSpec
from bench_matrix.workload.driving.defaults import DEFAULT_DATASET


@dataclass(frozen=True)
class TrainingSpec:
    """How a built-in reference model is trained on the dataset's training split."""

    epochs: int = 8
    batch_size: int = 16
    lr: float = 1e-3


MODEL_SUFFIXES = {".pt": ("pytorch", "torchscript"), ".pth": ("pytorch", "torchscript"),
                  ".pt2": ("pytorch", "torch_export"), ".onnx": ("onnx", "onnx"),
                  ".keras": ("tensorflow", "keras"), ".h5": ("tensorflow", "h5")}
SAVED_MODEL = ("tensorflow", "saved_model")  # a directory holding saved_model.pb
DEFAULT_LAYOUT = {"tensorflow": "nhwc"}  # every other framework: nchw


def file_kind(path: Path) -> tuple[str, str] | None:
    """(framework, format) of a model file or SavedModel directory, or None when it is not one we read."""
    if path.is_dir():
        return SAVED_MODEL if (path / "saved_model.pb").is_file() else None
    return MODEL_SUFFIXES.get(path.suffix.lower())


@dataclass(frozen=True)
class ModelSpec:
    """One model of the matrix and where it comes from (exactly one of builtin, file, factory)."""

    name: str
    framework: str
    builtin: str | None = None
    file: Path | None = None
    factory: str | None = None
    weights: Path | None = None
    python_path: tuple[Path, ...] = ()
    layout: str = "nchw"
    training: TrainingSpec = field(default_factory=TrainingSpec)
    inputs: tuple[TensorSpec, ...] = ()  # declared inputs; empty: read from the model file, else the dataset's
    task: str | None = None  # overrides the dataset's task for this model
    dataset: "DatasetSpec | None" = None  # this model's own dataset; None: the matrix's

    @property
    def source_format(self) -> str:
        """The SourceModel format this model arrives in (built-in: state_dict or keras; factory: state_dict)."""
        if self.file is None:
            return "keras" if self.framework == "tensorflow" else "state_dict"
        return (file_kind(self.file) or ("", "unknown"))[1]


@dataclass(frozen=True)
class Preprocess:
    """Preprocessing applied identically to every split: crop, resize, scale, normalise."""

    crop: tuple[int | None, int | None, int | None, int | None] | None = None  # top, bottom, left, right
    resize: tuple[int, int] | None = None  # height, width
    scale: float | None = None  # None: 1/255, for pixels 0..255 (data.py refuses other images then)
    mean: tuple[float, ...] | None = None
    std: tuple[float, ...] | None = None
    resize_shorter: int | None = None  # resize so the shorter side has this length (aspect ratio kept) ...
    center_crop: tuple[int, int] | None = None  # ... then cut the centre (height, width): torchvision's way


@dataclass(frozen=True)
class LabelSpec:
    """Which label columns to read and how they are normalised: y' = (y - offset) / scale."""

    columns: tuple[str, ...] = ("v", "w")
    offset: tuple[float, ...] | None = None
    scale: tuple[float, ...] | None = None


@dataclass(frozen=True)
class SplitSpec:
    """Fractions of the three disjoint splits and how samples are assigned to them."""

    train: float = 0.7
    calibration: float = 0.1
    test: float = 0.2
    by: str = "auto"  # auto: by group when the data has 3+ groups (circuits, recordings), else block


@dataclass(frozen=True)
class DatasetSpec:
    """The dataset: a built-in workload, an .npz (one array per input, labels y), DeepLearningStudio folders,
    image folders with one subfolder per class, or synthetic inputs of the models' shapes."""

    kind: str  # builtin | npz | folder | images | synthetic
    paths: tuple[Path, ...] = ()
    builtin: str = DEFAULT_DATASET  # the built-in workload (workload/driving/defaults.py)
    task: str = "regression"  # one of TASKS
    samples: int = 4000
    circuits: int = 20
    seed: int = 0
    preprocess: Preprocess = field(default_factory=Preprocess)
    labels: LabelSpec = field(default_factory=LabelSpec)
    split: SplitSpec = field(default_factory=SplitSpec)


@dataclass(frozen=True)
class Settings:
    """Measurement settings shared by every cell."""

    warmup_iterations: int = 20  # once per session, before its rounds
    warmup_s: float = 0.5
    window_s: float = 0.1  # each cell's timed window of each kind, once per round (docs/metrics.md §5)
    min_rounds: int = 5
    ci_target: float | None = None  # asked: every cell's p50 and speed-up intervals within ± this
    timing_budget_s: float = 3.0  # per cell: a model's rounds stop when its cells' share is spent
    processes: int = 2  # session processes per cell, timed in the same rounds: how they differ is measured
    memory_share: float = 0.5  # of the available memory, for a model's sessions loaded at once
    batch_size: int = 32
    threads: int = 1
    timeout_s: float = 600.0
    seed: int = 0
    eval_samples: int | None = None

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)


@dataclass(frozen=True)
class Selector:
    """A partial cell (some of model, framework, backend, strategy, precision, target)."""

    values: tuple[tuple[str, str], ...]

    def matches(self, cell: dict[str, str]) -> bool:
        return all(cell.get(key) == value for key, value in self.values)


@dataclass(frozen=True)
class Selection:
    """The cells a scenario's section selects: those among `cells` (None: every cell) not in `exclude`."""

    cells: tuple[Selector, ...] | None = None
    exclude: tuple[Selector, ...] = ()

    def selects(self, cell: dict[str, str]) -> bool:
        """True when the cell (as a dict) is among `cells` and not excluded."""
        chosen = self.cells is None or any(s.matches(cell) for s in self.cells)
        return chosen and not any(s.matches(cell) for s in self.exclude)


@dataclass(frozen=True)
class Matrix:
    """A loaded, validated matrix file."""

    path: Path
    name: str
    models: tuple[ModelSpec, ...]
    dataset: DatasetSpec
    strategies: dict[str, StrategySpec]
    axes: dict[str, tuple[str, ...]]
    include: tuple[Selector, ...]
    exclude: tuple[Selector, ...]
    settings: Settings
    backend_options: dict[str, dict[str, Any]] = field(default_factory=dict)  # per backend, its own options
    metrics: tuple[str, ...] = ()  # metric plugins to add to every cell's evaluation
    scenarios: dict[str, Any] = field(default_factory=dict)  # a selectable scenario's name -> its section
    requirements: Declared = field(default_factory=Declared)  # the top level's and each model's own
    lines: dict[tuple, int] = field(default_factory=dict, compare=False, repr=False)
    warnings: tuple[str, ...] = field(default=(), compare=False)  # located: retired keys it still uses

    def model(self, name: str) -> ModelSpec:
        return next(m for m in self.models if m.name == name)

    def dataset_of(self, model: ModelSpec) -> DatasetSpec:
        """The dataset a model is evaluated on: its own, or the matrix's."""
        return model.dataset or self.dataset

    def task_of(self, model: ModelSpec) -> str:
        return model.task or self.dataset_of(model).task

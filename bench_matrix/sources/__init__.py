"""The pristine source model of a cell: where it lives, its format, its content hash, and how to load it."""

from __future__ import annotations

from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

from bench_matrix.errors import UserError
from bench_matrix.named import resolve
from bench_matrix.tensors import TensorSpec, specs_from_list, specs_to_list

# keras_qat: a quantisation-aware-trained Keras model, written by the tfmot trainer (loaded in tfmot's scope)
FORMATS = ("torchscript", "torch_export", "state_dict", "onnx", "keras", "h5", "saved_model", "keras_qat")


# Each framework's loader, imported when a model is loaded (each imports its framework); our tfmot trainer's
# output (format keras_qat, in the workspace cache) has its own.
LOADERS = {"pytorch": "bench_matrix.sources.pytorch:load_module",
           "tensorflow": "bench_matrix.sources.tensorflow:load_keras"}
QAT_LOADER = "bench_matrix.sources.keras_qat:load_source"


class ModelFileError(UserError, ValueError):
    """A model file, weights file or factory bench-matrix will not or cannot load: the user's to fix (a
    UserError), and a ValueError as the loaders' errors always were."""


@dataclass(frozen=True)
class SourceModel:
    """A model file as the user (or the built-in trainer) gave it; every cell starts from this."""

    name: str
    framework: str
    format: str  # one of FORMATS
    path: Path
    sha256: str
    inputs: tuple[TensorSpec, ...]  # the model's named inputs, in order: one sample's shape and dtype each
    factory: str | None = None  # 'module:function' building the module a state_dict belongs to
    python_path: tuple[str, ...] = ()
    origin: str | None = None  # the user's file this is a fine-tuned copy of; None: `path` is the user's
    code_sha256: str | None = None  # SHA-256 of the factory's module file (sources.code.factory_sha256)

    def identity(self) -> dict[str, Any]:
        """Everything that decides what this source computes, wherever its files lie: the cache keys' part."""
        return {"sha256": self.sha256, "framework": self.framework, "format": self.format,
                "inputs": specs_to_list(self.inputs), "factory": self.factory, "code": self.code_sha256}

    @property
    def input_shape(self) -> tuple[int, ...]:
        """The sample shape of a single-input model (free axes as 8); ModelFileError for several inputs."""
        if len(self.inputs) != 1:
            names = ", ".join(i.describe() for i in self.inputs)
            raise ModelFileError(f"{self.label}: the model has {len(self.inputs)} inputs ({names}); this "
                                 f"conversion takes models with exactly one input")
        return tuple(8 if d is None else d for d in self.inputs[0].shape)

    @property
    def label(self) -> str:
        """How messages name the model file: the user's path, and the cache copy's path after it."""
        return f"{self.origin} (fine-tuned copy {self.path})" if self.origin else str(self.path)

    def load(self) -> Any:
        """A fresh framework object (never shared by strategies): nn.Module, ScriptModule, Keras model or ONNX
        file path (read by sources.onnx_file.load_onnx); ModelFileError for an unsafe or unreadable file."""
        try:
            return self._load()
        except (FileNotFoundError, PermissionError, IsADirectoryError) as exc:
            raise ModelFileError(f"{self.label}: cannot be read ({exc.strerror}: {exc.filename})") from None

    def _load(self) -> Any:
        if self.framework == "onnx":
            return self.path
        loader = QAT_LOADER if self.format == "keras_qat" else LOADERS.get(self.framework)
        if loader is None:
            raise ValueError(f"no loader for framework {self.framework!r}")
        return resolve(loader)(self)

    def to_dict(self) -> dict[str, Any]:
        data = asdict(self)
        data["path"] = str(self.path)
        data["inputs"] = specs_to_list(self.inputs)
        return data

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> "SourceModel":
        return cls(**{**data, "path": Path(data["path"]), "inputs": specs_from_list(data["inputs"]),
                      "python_path": tuple(data.get("python_path", ()))})

"""Where a factory's Python module lives, found without importing it, and the hash of its source."""

from __future__ import annotations

import sys
from importlib.machinery import PathFinder
from pathlib import Path
from typing import TYPE_CHECKING, Sequence

from bench_matrix.workspace import file_sha256

if TYPE_CHECKING:
    from bench_matrix.matrix.spec import ModelSpec

# the modules that build and train each framework's built-in models
BUILTIN_CODE = {"pytorch": ("bench_matrix.workload.pilotnet_torch", "bench_matrix.workload.train"),
                "tensorflow": ("bench_matrix.workload.pilotnet_keras", "bench_matrix.workload.train")}


def module_file(module: str, python_path: Sequence[str] = ()) -> Path | None:
    """The file defining `module` ('pkg.sub'), searched in python_path then sys.path; None when not found."""
    search: list[str] | None = [*map(str, python_path), *sys.path]
    spec = None
    for part in range(1, module.count(".") + 2):
        spec = PathFinder.find_spec(".".join(module.split(".")[:part]), search)
        if spec is None:
            return None
        search = list(spec.submodule_search_locations or [])
    return Path(spec.origin) if spec is not None and spec.has_location and spec.origin else None


def factory_sha256(factory: str | None, python_path: Sequence[str] = ()) -> str | None:
    """SHA-256 of the source file of a factory's module ('module:function' or 'module'); None: not found."""
    if not factory:
        return None
    path = module_file(factory.split(":")[0], python_path)
    return file_sha256(path) if path is not None and path.is_file() else None


def model_code(spec: "ModelSpec") -> str | None:
    """The hash of the code that builds a model: its factory's module, or a built-in's model and training
    modules; None for a model file."""
    if not spec.builtin:
        return factory_sha256(spec.factory, tuple(map(str, spec.python_path)))
    return ",".join(str(factory_sha256(module)) for module in BUILTIN_CODE[spec.framework])

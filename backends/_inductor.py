"""What the Inductor backends (torch_compile, aot_inductor) share: the toolchain probe, where Inductor's
caches live, which sources they compile, and calling a session at the batch sizes a cell uses."""

from __future__ import annotations

import atexit
import functools
import importlib.util
import os
import shutil
import sys
import sysconfig
import tempfile
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from bench_matrix.plugin import SourceModel, TensorSpec, example_inputs, installed_versions

from ._torch import TorchSession, cuda_reasons

LIBRARIES = ("torch", "triton")  # Inductor generates C++ (CPU) and Triton (NVIDIA GPU) kernels
WARM_CALLS = 3  # per batch size at load: compile, then record CUDA graphs (reduce-overhead) and replay them
SOURCES = ("state_dict", "torch_export")  # an nn.Module (factory + weights) or a torch.export program


def inductor_versions() -> dict[str, str]:
    return installed_versions(*LIBRARIES)


def toolchain_reasons(target: str, precision: str, python_headers: bool) -> list[str]:
    """Why Inductor cannot compile for `target` here: every missing piece, each with its fix."""
    reasons = cuda_reasons(precision) if target != "cpu" else []
    compiler = os.environ.get("CXX", "clang++" if sys.platform == "darwin" else "g++")  # Inductor's cpp.cxx
    if shutil.which(compiler) is None:
        reasons.append(f"no C++ compiler found (Inductor compiles C++ kernels and wrappers): {compiler!r} is "
                       f"not on PATH; install g++ (apt-get install g++) or set CXX to a C++ compiler")
    headers = Path(sysconfig.get_path("include")) / "Python.h"
    if (python_headers or target != "cpu") and not headers.is_file():
        what = "its CPU kernels as Python extensions" if target == "cpu" else "Triton's kernel launchers"
        reasons.append(f"Python's C headers are missing ({headers}; Inductor compiles {what}): install the "
                       f"python{sys.version_info[0]}.{sys.version_info[1]}-dev package")
    if target != "cpu" and importlib.util.find_spec("triton") is None:
        reasons.append("Triton is not installed (Inductor generates Triton kernels for NVIDIA GPUs): install "
                       "the triton release that this torch build names (pip install triton)")
    return reasons


def source_reason(backend: str, source_format: str) -> str | None:
    """Why `backend` cannot compile a source of `source_format` (a TorchScript file), or None."""
    if source_format in SOURCES:
        return None
    kind = "a TorchScript file" if source_format == "torchscript" else f"a {source_format!r} source"
    return (f"{backend} compiles an nn.Module or a torch.export program (TorchDynamo and torch.export trace "
            f"Python code, not TorchScript), but this model is {kind}; give it as factory + weights (a "
            f"state_dict) or as a torch.export .pt2 file")


def fixed_shapes_reason(backend: str, source: SourceModel) -> str | None:
    """Why the model cannot be compiled before its data is seen: an input with a free axis, or None."""
    free = [spec.describe() for spec in source.inputs if None in spec.shape]
    if not free:
        return None
    return (f"{source.label}: {backend} compiles for fixed sample shapes at load or conversion, before any "
            f"data is seen, but input {', '.join(free)} has a free axis; declare its length in the model's "
            f"`inputs:`")


def no_precompiled_headers() -> dict[str, bool]:
    """Inductor configs that keep its precompiled headers off: Inductor keeps them in a global directory
    (tempdir/torchinductor_USER), outside TORCHINDUCTOR_CACHE_DIR, where a warm one would shorten compiles."""
    return {"cpp_cache_precompile_headers": False, "aot_inductor.precompile_headers": False}


@functools.cache
def private_cache(warm: Path | None = None) -> str:
    """Point Inductor's and Triton's caches at a fresh directory of this process, removed when it exits
    (holding a copy of `warm`, a cache an artifact carries): whatever the user's cache holds is never used,
    and nothing is left behind."""
    import torch._inductor.config as inductor_config

    directory = tempfile.mkdtemp(prefix="bench-matrix-inductor-")
    atexit.register(shutil.rmtree, directory, ignore_errors=True)
    if warm is not None and warm.is_dir():
        shutil.copytree(warm, directory, dirs_exist_ok=True)
    os.environ["TORCHINDUCTOR_CACHE_DIR"] = directory
    os.environ["TRITON_CACHE_DIR"] = os.path.join(directory, "triton")
    inductor_config.cpp_cache_precompile_headers = False  # as no_precompiled_headers(), for the whole process
    inductor_config.aot_inductor.precompile_headers = False
    return directory


def cell_batches(max_batch: int) -> list[int]:
    """The batch sizes a cell runs: 1 (latency) and max_batch (throughput), largest first."""
    return sorted({1, max_batch}, reverse=True)


def run_batches(session: TorchSession, specs: Sequence[TensorSpec], batches: Sequence[int],
                mark_dynamic: bool = False) -> float:
    """Call the session WARM_CALLS times at each batch size (the batch axis marked dynamic for batches above 1
    when `mark_dynamic`); the seconds it took."""
    import torch

    begin = time.perf_counter()
    for batch in batches:
        prepared = session.prepare(example_inputs(specs, batch))
        if mark_dynamic and batch > 1:
            for tensor in prepared:
                torch._dynamo.mark_dynamic(tensor, 0)
        for _ in range(WARM_CALLS):
            session.execute(prepared)
    return time.perf_counter() - begin


def compiled_graphs() -> tuple[int, int]:
    """How many graphs TorchDynamo has compiled in this process, and how many graph breaks it met."""
    from torch._dynamo.utils import counters

    return counters["stats"]["unique_graphs"], sum(counters["graph_break"].values())


def compile_now(session: TorchSession, source: SourceModel, batches: Sequence[int],
                dynamic: bool) -> dict[str, Any]:
    """Call a torch.compile'd session at every batch size so that TorchDynamo compiles it now; what it
    compiled, and the seconds it took (compile_s)."""
    graphs, breaks = compiled_graphs()
    cached = cache_use()
    seconds = run_batches(session, source.inputs, batches, dynamic)
    now_graphs, now_breaks = compiled_graphs()
    if now_graphs == graphs:
        raise RuntimeError(f"torch.compile compiled no graph of {source.label} (TorchDynamo ran it "
                           f"eagerly): the cell would measure eager PyTorch")
    return {"compile_s": round(seconds, 3), "compiled_batches": list(batches), "graphs": now_graphs - graphs,
            "graph_breaks": now_breaks - breaks, **{k: n - cached[k] for k, n in cache_use().items()}}


def cache_use() -> dict[str, int]:
    """How many Inductor graphs the process took from its cache (hits) and compiled (misses) so far."""
    from torch._dynamo.utils import counters

    found = counters["inductor"]
    return {"cache_hits": int(found["fxgraph_cache_hit"]), "cache_misses": int(found["fxgraph_cache_miss"])}

"""PyTorch's compilers: torch.compile (TorchDynamo + Inductor, compiled when the cell loads) and AOTInductor
(a package compiled ahead of time: the artifact)."""

from __future__ import annotations

import shutil
from pathlib import Path
from typing import Any

from bench_matrix.plugin import Backend, ConvertRequest, Session, SourceModel, StrategySpec, Support, \
    specs_from_list, specs_to_list

from ._inductor import cell_batches, compile_now, fixed_shapes_reason, inductor_versions, \
    no_precompiled_headers, private_cache, run_batches, source_reason, toolchain_reasons
from ._torch import TorchSession, exact_fp32, missing_torch, pin_threads, place, quiet_torch, torch_dtype
from .torch_tensorrt import export

SUPPORTS = (Support(("pytorch",), ("none",), ("fp32",), ("cpu",)),
            Support(("pytorch",), ("none",), ("fp32", "fp16", "bf16"), ("cuda",)))
MODES = ("default", "reduce-overhead", "max-autotune", "max-autotune-no-cudagraphs")
CUDA_GRAPH_MODES = ("reduce-overhead", "max-autotune")
AOT_MODES = ("default", "max-autotune-no-cudagraphs")  # an AOTInductor package has no CUDA graphs
PACKAGE = "model.pt2"
# a package runs its generated kernels unseen by torch.profiler (only its fallbacks to aten ops are recorded):
# a profile counts a call's time outside those under this name
AOT_KERNELS = "aot_inductor::generated_kernels"
CACHE = "inductor-cache"  # the Inductor cache a torch_compile artifact carries: its compilation, done once


class InductorBackend(Backend):
    """What both compilers share: their libraries, the toolchain probe and the sources they take."""

    supports = SUPPORTS
    devices = {"cuda": "cuda"}
    python_headers = False  # whether the generated CPU code includes Python's C headers

    def versions(self) -> dict[str, str]:
        return inductor_versions()

    def probe(self, target: str, precision: str) -> str | None:
        return missing_torch() or "; ".join(toolchain_reasons(target, precision, self.python_headers)) or None

    def option_reason(self, step: StrategySpec, source_format: str) -> str | None:
        return source_reason(self.name, source_format)

    def check(self, source: SourceModel) -> None:
        """Raise the reason this source cannot be compiled, if there is one."""
        if reason := source_reason(self.name, source.format) or fixed_shapes_reason(self.name, source):
            raise ValueError(reason)

    def options_of(self, request: ConvertRequest) -> dict[str, Any]:
        """The matrix's options for this backend over the declared defaults."""
        return {**{key: schema["default"] for key, schema in self.options.items()}, **request.options}


class TorchCompileBackend(InductorBackend):
    """The source model, compiled by torch.compile at load for the cell's batch sizes, before any timing."""

    name = "torch_compile"
    slow_start = ("compiles the model with Inductor when converting, about a minute a cell on 2 cores (once: "
                  "the artifact keeps the compilation, and every load takes it from there)")
    description = "torch.compile (TorchDynamo + Inductor), compiled at load for the cell's batch sizes"
    python_headers = True
    options = {
        "mode": {"enum": list(MODES), "default": "default",
                 "description": "torch.compile mode; reduce-overhead and max-autotune add CUDA graphs "
                                "on cuda"},
        "dynamic": {"type": "boolean", "default": False,
                    "description": "false: a graph per batch size; true: the batch axis symbolic (one graph "
                                   "for batches of 2 and more, batch 1 its own)"},
        "fullgraph": {"type": "boolean", "default": False,
                      "description": "true: fail on a graph break instead of running that part eagerly"},
    }

    revision = 2  # the artifact carries the Inductor cache of its compilation

    def convert(self, request: ConvertRequest) -> dict[str, Any]:
        """A copy of the source file, compiled once here for the cell's batch sizes: the artifact carries that
        compilation as an Inductor cache, so every load of it compiles from the cache."""
        source = request.source
        self.check(source)
        shutil.copy2(source.path, request.out_dir / source.path.name)
        meta = {"source": {**source.to_dict(), "path": source.path.name}, "max_batch": request.max_batch,
                "options": self.options_of(request), "cache": CACHE}
        pin_threads(request.threads)
        cache = Path(private_cache())
        facts = _compiled(request.out_dir, meta, request.target, request.precision)[1]
        shutil.copytree(cache, request.out_dir / CACHE)
        return {**meta, "convert_compile_s": facts["compile_s"]}

    def load(self, artifact_dir: Path, meta: dict[str, Any], target: str, precision: str,
             threads: int) -> Session:
        """Compile for batch 1 and max_batch with the threads pinned, from a copy of the artifact's Inductor
        cache; compile_s is that part of the load, cache_hits and cache_misses say how it went."""
        pin_threads(threads)
        private_cache(artifact_dir / meta["cache"] if "cache" in meta else None)
        compiled, facts = _compiled(artifact_dir, meta, target, precision)
        return TorchSession(compiled, target, precision, facts)


def _compiled(artifact_dir: Path, meta: dict[str, Any], target: str, precision: str) -> tuple[Any, dict]:
    """The artifact's source compiled by torch.compile now, at each of the cell's batch sizes, and the facts."""
    import torch

    source = SourceModel.from_dict({**meta["source"], "path": str(artifact_dir / meta["source"]["path"])})
    options = meta["options"]
    torch._dynamo.reset()  # a second load in one process must compile again, not reuse the first graphs
    with quiet_torch(captured=True):
        module = place(source.load(), target, precision)
        compiled = torch.compile(module, mode=options["mode"], fullgraph=options["fullgraph"],
                                 dynamic=None if options["dynamic"] else False)
        facts = compile_now(TorchSession(compiled, target, precision), source,
                            cell_batches(meta["max_batch"]), options["dynamic"])
    facts.update(options, cuda_graphs=target != "cpu" and options["mode"] in CUDA_GRAPH_MODES)
    return compiled, facts


class AotInductorBackend(InductorBackend):
    """The model exported with a dynamic batch axis and compiled ahead of time into an AOTInductor package."""

    name = "aot_inductor"
    slow_start = "compiles the model ahead of time with Inductor when converting, half a minute or more a cell"
    description = "AOTInductor: torch.export + Inductor compiled ahead of time into a .pt2 package"
    options = {
        "mode": {"enum": list(AOT_MODES), "default": "default",
                 "description": "the torch.compile mode whose Inductor settings compile the package"},
    }

    def convert(self, request: ConvertRequest) -> dict[str, Any]:
        """Export for batches 1..max_batch and compile into model.pt2, Inductor's caches inside out_dir."""
        import torch
        from torch._inductor.utils import fresh_cache

        self.check(request.source)
        torch.set_num_threads(request.threads)
        options = self.options_of(request)
        configs = inductor_configs(options["mode"], request.target)
        device = "cpu" if request.target == "cpu" else "cuda"
        if device == "cuda":
            exact_fp32()  # Inductor picks its matmul kernels with TF32 allowed or not, when it compiles
        with quiet_torch(captured=True), fresh_cache(dir=str(request.out_dir)):
            module = place(request.source.load(), request.target, request.precision)
            with torch.no_grad():
                program, _ = export(module, request.source.inputs, request.max_batch, device,
                                    torch_dtype(request.precision), request.seed)
            torch._inductor.aoti_compile_and_package(program, package_path=str(request.out_dir / PACKAGE),
                                                     inductor_configs=dict(configs))
        return {"file": PACKAGE, "inputs": specs_to_list(request.source.inputs),
                "max_batch": request.max_batch, "mode": options["mode"], "inductor_configs": configs}

    def load(self, artifact_dir: Path, meta: dict[str, Any], target: str, precision: str,
             threads: int) -> Session:
        """Load the package and call it at each batch size (the first calls set its runtime up, untimed)."""
        import torch

        pin_threads(threads)
        private_cache()
        with quiet_torch(captured=True):
            model = torch._inductor.aoti_load_package(str(artifact_dir / meta["file"]))
        facts = {"mode": meta["mode"], "inductor_configs": meta["inductor_configs"],
                 "batch_range": [1, meta["max_batch"]]}
        session = TorchSession(model, target, precision, facts, profiled_as=AOT_KERNELS)
        run_batches(session, specs_from_list(meta["inputs"]), cell_batches(meta["max_batch"]))
        return session


def inductor_configs(mode: str, target: str) -> dict[str, Any]:
    """The Inductor settings of a package: the mode's, precompiled headers off (they would be written outside
    out_dir) and, on the CPU, the thread count read at run time, not fixed at compile time (an artifact serves
    every `threads` setting)."""
    import torch

    configs: dict[str, Any] = {**torch._inductor.list_mode_options(mode), **no_precompiled_headers()}
    if target == "cpu":
        configs["cpp.dynamic_threads"] = True
    return dict(sorted(configs.items()))

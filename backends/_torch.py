"""What the two PyTorch backends share: versions, GPU probe, thread pinning, quantised engine, the session."""

from __future__ import annotations

import warnings
from collections.abc import Iterator
from contextlib import contextmanager, suppress
from typing import TYPE_CHECKING, Any

import numpy as np

from bench_matrix import hardware
from bench_matrix.backends.base import Backend, Session
from bench_matrix.measure.env import installed_versions


if TYPE_CHECKING:
    import torch


def torch_versions() -> dict[str, str]:
    return installed_versions("torch")


def probe_torch(target: str) -> str | None:
    """Why torch cannot run on `target` here (every missing piece), or None."""
    if target == "cpu":
        return None
    reasons = [reason] if (reason := hardware.no_gpu_reason()) else []
    import torch

    if torch.version.cuda is None:
        reasons.append(f"torch {torch.__version__} is a CPU-only build (install a CUDA build of torch)")
    elif not reasons and not torch.cuda.is_available():
        reasons.append(f"torch {torch.__version__} (CUDA {torch.version.cuda}) cannot use the GPU: "
                       f"torch.cuda.is_available() is False (is the NVIDIA driver too old for CUDA "
                       f"{torch.version.cuda}?)")
    return "; ".join(reasons) or None


def pin_threads(threads: int) -> None:
    """Use exactly `threads` intra-op threads and one inter-op thread."""
    import torch

    torch.set_num_threads(threads)
    if torch.get_num_interop_threads() != 1:
        # Settable once per process and only before inter-op work; inference runs intra-op threads only,
        # and the session's info() records the value in force.
        with suppress(RuntimeError):
            torch.set_num_interop_threads(1)


def use_engine(engine: str | None = None) -> str:
    """Select the quantised engine (`engine`, or x86 where supported, else fbgemm) and return its name."""
    import torch

    supported = torch.backends.quantized.supported_engines
    engine = engine or ("x86" if "x86" in supported else "fbgemm")
    if engine not in supported:
        raise RuntimeError(f"the artifact was quantised for torch's {engine!r} engine, which torch "
                           f"{torch.__version__} here lacks (it has {', '.join(supported)}); convert it again")
    torch.backends.quantized.engine = engine
    return engine


@contextmanager
def quiet_torch(captured: bool = False) -> Iterator[None]:
    """Silence torch's deprecation notices (torch.ao, torch.jit, the TorchScript ONNX exporter); `captured`
    also silences the tracer's notes on tensor-to-Python conversions, harmless in an already captured graph
    (an FX-quantised model's scales, a torch.export program's shape guards)."""
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", category=DeprecationWarning)
        warnings.filterwarnings("ignore", category=FutureWarning)
        warnings.filterwarnings("ignore", message="(reduce_range will be deprecated|no signature found for"
                                                  "|torch.quantize_per_tensor)")
        if captured:
            warnings.filterwarnings("ignore", message="Converting a tensor to a Python")
        yield


def place(module: "torch.nn.Module", target: str, precision: str) -> "torch.nn.Module":
    """The module on the target's device, in half precision for fp16."""
    if target == "cuda":
        module = module.to("cuda")
    return module.half() if precision == "fp16" else module


class TorchSession(Session):
    """A torch module (eager or TorchScript) run under inference_mode on the CPU or one CUDA GPU."""

    def __init__(self, module: "torch.nn.Module", target: str, precision: str):
        import torch

        self._torch = torch
        self._module = module
        self._device = torch.device("cuda" if target == "cuda" else "cpu")
        self._dtype = torch.float16 if precision == "fp16" else torch.float32
        self._sync = target == "cuda"

    def prepare(self, x: np.ndarray) -> "torch.Tensor":
        tensor = self._torch.from_numpy(np.ascontiguousarray(x, dtype=np.float32))
        return tensor.to(self._device, self._dtype)

    def execute(self, prepared: "torch.Tensor") -> Any:
        with self._torch.inference_mode():
            out = self._module(prepared)
        if self._sync:
            self._torch.cuda.synchronize()
        return out

    def fetch(self, outputs: Any) -> np.ndarray:
        out = outputs[0] if isinstance(outputs, (tuple, list)) else outputs
        return out.float().cpu().numpy()

    def info(self) -> dict[str, Any]:
        return {"device": str(self._device), "threads": self._torch.get_num_threads(),
                "interop_threads": self._torch.get_num_interop_threads()}


class TorchBackend(Backend):
    """What the PyTorch-runtime backends share: their library versions and their probe."""

    def versions(self) -> dict[str, str]:
        return torch_versions()

    def probe(self, target: str, precision: str) -> str | None:
        return probe_torch(target)

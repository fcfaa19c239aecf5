"""What the PyTorch backends share: versions, GPU probe, thread pinning, quantised engine, dtypes, the session."""

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

# The dtype a module computes in at each precision; int8 models take and return float32.
DTYPES = {"fp32": "float32", "fp16": "float16", "bf16": "bfloat16", "int8": "float32"}


def torch_versions() -> dict[str, str]:
    return installed_versions("torch")


def torch_dtype(precision: str) -> "torch.dtype":
    """The torch dtype of a module's parameters and inputs at `precision`."""
    import torch

    return getattr(torch, DTYPES[precision])


def cuda_reasons(precision: str, what: str | None = None) -> list[str]:
    """Why torch cannot run `precision` on an NVIDIA GPU here: every missing piece, each with its fix."""
    reasons = [reason] if (reason := hardware.no_gpu_reason()) else []
    import torch

    if torch.version.cuda is None:
        reasons.append(f"torch {torch.__version__} is a CPU-only build (install a CUDA build of torch)")
    elif mismatch := hardware.cuda_mismatch_reason("torch", torch.version.cuda):
        reasons.append(mismatch)
    elif not reasons and not torch.cuda.is_available():
        reasons.append(f"torch {torch.__version__} (CUDA {torch.version.cuda}) cannot use the GPU that nvidia-smi "
                       f"lists: torch.cuda.is_available() is False (check CUDA_VISIBLE_DEVICES and the GPU's "
                       f"compute mode)")
    if too_old := hardware.precision_reason(precision, what):
        reasons.append(too_old)
    elif precision == "bf16" and not reasons and not torch.cuda.is_bf16_supported(including_emulation=False):
        reasons.append(f"{torch.cuda.get_device_name()} has no native bf16 (torch.cuda.is_bf16_supported("
                       f"including_emulation=False) is False); bf16 needs compute capability 8.0 or newer")
    return reasons


def pin_threads(threads: int) -> None:
    """Use exactly `threads` intra-op threads and one inter-op thread."""
    import torch

    torch.set_num_threads(threads)
    if torch.get_num_interop_threads() != 1:
        # Settable once per process and only before inter-op work; inference runs intra-op threads only,
        # and the session's info() records the value in force.
        with suppress(RuntimeError):
            torch.set_num_interop_threads(1)


def exact_fp32() -> None:
    """Switch TensorFloat-32 off for cuBLAS matmuls and cuDNN convolutions: fp32 on a GPU means IEEE fp32."""
    import torch

    if hasattr(torch.backends.cudnn, "conv"):  # torch 2.9+; the allow_tf32 flags are deprecated there
        torch.backends.cuda.matmul.fp32_precision = "ieee"
        torch.backends.cudnn.conv.fp32_precision = "ieee"
    else:
        torch.backends.cuda.matmul.allow_tf32 = False
        torch.backends.cudnn.allow_tf32 = False


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
    """The module on the target's device (a GPU for cuda and tensorrt), in the precision's dtype."""
    import torch

    if target != "cpu":
        module = module.to("cuda")
    dtype = torch_dtype(precision)
    return module if dtype == torch.float32 else module.to(dtype)


class TorchSession(Session):
    """A torch module (eager, TorchScript or Torch-TensorRT) run under inference_mode on the CPU or one GPU."""

    def __init__(self, module: "torch.nn.Module", target: str, precision: str, facts: dict[str, Any] | None = None):
        import torch

        self._torch = torch
        self._module = module
        self._device = torch.device("cpu" if target == "cpu" else "cuda")
        self._dtype = torch_dtype(precision)
        self._sync = target != "cpu"
        self._facts = facts or {}
        if self._sync:
            exact_fp32()

    def prepare(self, x: np.ndarray) -> "torch.Tensor":
        """The batch on the device in the module's dtype: copied to the GPU here, outside the timed call."""
        tensor = self._torch.from_numpy(np.ascontiguousarray(x, dtype=np.float32))
        return tensor.to(self._device, self._dtype)

    def execute(self, prepared: "torch.Tensor") -> Any:
        with self._torch.inference_mode():
            out = self._module(prepared)
        if self._sync:
            self._torch.cuda.synchronize()
        return out

    def fetch(self, outputs: Any) -> np.ndarray:
        """The first output as a float32 host array (copied back from the GPU)."""
        out = outputs[0] if isinstance(outputs, (tuple, list)) else outputs
        return out.float().cpu().numpy()

    def info(self) -> dict[str, Any]:
        info = {"device": str(self._device), "threads": self._torch.get_num_threads(),
                "interop_threads": self._torch.get_num_interop_threads(), **self._facts}
        if self._sync:
            info.update(dtype=str(self._dtype).removeprefix("torch."), tensor_float_32=False)
        return info


class TorchBackend(Backend):
    """What the PyTorch-runtime backends share: their library versions and their probe."""

    def versions(self) -> dict[str, str]:
        return torch_versions()

    def probe(self, target: str, precision: str) -> str | None:
        return None if target == "cpu" else "; ".join(cuda_reasons(precision)) or None

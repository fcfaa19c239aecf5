"""What the PyTorch backends share: versions, GPU probe, thread pinning, quantised engine, dtypes, the session."""

from __future__ import annotations

import importlib.util
from collections.abc import Sequence
from contextlib import suppress
from typing import TYPE_CHECKING, Any

import numpy as np

from bench_matrix.plugin import Backend, Inputs, Profile, Session, TensorSpec, cuda_mismatch_reason, \
    example_inputs, flat_outputs, installed_versions, no_gpu_reason, precision_reason, quiet_torch, use_engine

from ._torch_profile import torch_profile


__all__ = ["quiet_torch", "use_engine"]  # re-exported for the torch backends

if TYPE_CHECKING:
    import torch

# The dtype a module computes in at each precision; int8 models take and return float32.
DTYPES = {"fp32": "float32", "fp16": "float16", "bf16": "bfloat16", "int8": "float32"}
GPU_PROFILE_REASON = ("torch.profiler's CPU times of a GPU cell are kernel launches, not the kernels' run "
                      "time, and its GPU kernel times (ProfilerActivity.CUDA) are not attributed to "
                      "operators yet")


def torch_dtype(precision: str) -> "torch.dtype":
    """The torch dtype of a module's parameters and inputs at `precision`."""
    import torch

    return getattr(torch, DTYPES[precision])


def missing_torch() -> str | None:
    """Why torch cannot be imported here (found without importing it: a device that measures only), or
    None."""
    if importlib.util.find_spec("torch") is None:
        return ("torch is not installed: pip install torch (a build for this machine; a Jetson's: NVIDIA's "
                "wheels)")
    return None


def cuda_reasons(precision: str, what: str | None = None) -> list[str]:
    """Why torch cannot run `precision` on an NVIDIA GPU here: every missing piece, each with its fix."""
    reasons = [reason] if (reason := no_gpu_reason()) else []
    import torch

    if torch.version.cuda is None:
        reasons.append(f"torch {torch.__version__} is a CPU-only build (install a CUDA build of torch)")
    elif mismatch := cuda_mismatch_reason("torch", torch.version.cuda):
        reasons.append(mismatch)
    elif not reasons and not torch.cuda.is_available():
        reasons.append(f"torch {torch.__version__} (CUDA {torch.version.cuda}) cannot use the GPU that nvidia-smi "
                       f"lists: torch.cuda.is_available() is False (check CUDA_VISIBLE_DEVICES and the GPU's "
                       f"compute mode)")
    if too_old := precision_reason(precision, what):
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
    """Switch TensorFloat-32 off for cuBLAS matmuls and cuDNN convolutions: fp32 on a GPU means IEEE fp32.

    Through the allow_tf32 flags, which set cuDNN's convolution and RNN precisions together: torch 2.13's
    newer per-operator flags (cudnn.conv.fp32_precision) left them apart, and every torch.export later in
    the process (it reads the flags) failed "cuDNN conv and cuDNN RNN have different TF32 flags"."""
    import torch

    torch.backends.cuda.matmul.allow_tf32 = False
    torch.backends.cudnn.allow_tf32 = False


def place(module: "torch.nn.Module", target: str, precision: str) -> "torch.nn.Module":
    """The module on the target's device (a GPU for cuda and tensorrt), in the precision's dtype."""
    import torch

    if target != "cpu":
        module = module.to("cuda")
    dtype = torch_dtype(precision)
    return module if dtype == torch.float32 else module.to(dtype)


def as_tensors(inputs: Inputs, device: "torch.device | str", dtype: "torch.dtype") -> tuple["torch.Tensor", ...]:
    """Every input as a tensor on `device`, in the inputs' order: floating ones (read as float32) in `dtype`,
    integer ones (token ids, masks) in their own dtype."""
    import torch

    tensors = []
    for array in inputs.values():
        if np.issubdtype(array.dtype, np.floating):
            tensors.append(torch.from_numpy(np.ascontiguousarray(array, dtype=np.float32)).to(device, dtype))
        else:
            tensors.append(torch.from_numpy(np.ascontiguousarray(array)).to(device))
    return tuple(tensors)


def example_tensors(specs: Sequence[TensorSpec], device: str, dtype: "torch.dtype", seed: int,
                    batch: int = 2) -> tuple["torch.Tensor", ...]:
    """A batch to trace or export with (2 samples, not 1, so that nothing specialises on a size-1 batch)."""
    return as_tensors(example_inputs(specs, batch, seed), device, dtype)


def flat_module(module: "torch.nn.Module", example: tuple["torch.Tensor", ...]) -> tuple["torch.nn.Module", int]:
    """`module` itself when it returns one tensor, else a module returning its outputs as a flat tuple in
    flat_outputs' order (dicts by sorted key), so that traces and exports see the order sessions fetch in
    (traced around a TorchScript module, which torch.onnx cannot trace inside a Python one); with how many
    outputs it returns."""
    import torch

    with torch.no_grad():
        outputs = module(*example)
    if isinstance(outputs, torch.Tensor):
        return module, 1

    class FlatOutputs(torch.nn.Module):
        def __init__(self, inner: torch.nn.Module):
            super().__init__()
            self.inner = inner

        def forward(self, *args: torch.Tensor) -> tuple[torch.Tensor, ...]:
            return tuple(flat_outputs(self.inner(*args)))

    flat = FlatOutputs(module)
    flat.training = False  # set, not .eval(): a torch.export module refuses train() and eval()
    if isinstance(module, torch.jit.ScriptModule):
        with torch.no_grad():
            flat = torch.jit.trace(flat, example)
    return flat, len(flat_outputs(outputs))


class TorchSession(Session):
    """A torch module (eager, TorchScript or Torch-TensorRT) run under inference_mode on the CPU or one GPU; the
    module is called with every input positionally, in the inputs' order."""

    def __init__(self, module: "torch.nn.Module", target: str, precision: str,
                 facts: dict[str, Any] | None = None, profiled_as: str | None = None):
        """`profiled_as`: the name under which a profile counts the call's time in no recorded op (what runs
        without the profiler seeing it), or None to leave that time out."""
        import torch

        self._torch = torch
        self._module = module
        self._device = torch.device("cpu" if target == "cpu" else "cuda")
        self._dtype = torch_dtype(precision)
        self._precision = precision
        self._profiled_as = profiled_as
        self._sync = target != "cpu"
        self._facts = facts or {}
        if self._sync:
            exact_fp32()

    def prepare(self, inputs: Inputs) -> tuple["torch.Tensor", ...]:
        """The batch on the device (floating inputs in the module's dtype): copied to the GPU here, outside the
        timed call."""
        return as_tensors(inputs, self._device, self._dtype)

    def execute(self, prepared: tuple["torch.Tensor", ...]) -> Any:
        with self._torch.inference_mode():
            out = self._module(*prepared)
        if self._sync:
            self._torch.cuda.synchronize()
        return out

    def fetch(self, outputs: Any) -> list[np.ndarray]:
        """Every output (flat_outputs' order) as a float32 host array, copied back from the GPU."""
        return [out.float().cpu().numpy() for out in flat_outputs(outputs)]

    def profile(self, prepared: tuple["torch.Tensor", ...], calls: int) -> Profile:
        """torch.profiler's self CPU time per op over `calls` calls (docs/metrics.md, Profiles); none on a
        GPU."""
        if self._sync:
            return Profile(reason=GPU_PROFILE_REASON)
        compute = "fp32" if self._precision == "int8" else self._precision  # an int8 model's float parts
        return torch_profile(lambda: self.execute(prepared), calls, compute, self._profiled_as)

    def info(self) -> dict[str, Any]:
        info = {"device": str(self._device), "threads": self._torch.get_num_threads(),
                "interop_threads": self._torch.get_num_interop_threads(), **self._facts}
        if self._sync:
            info.update(dtype=str(self._dtype).removeprefix("torch."), tensor_float_32=False)
        return info


class TorchBackend(Backend):
    """What the PyTorch-runtime backends share: their library versions, their probe and their GPU target."""

    devices = {"cuda": "cuda"}

    def versions(self) -> dict[str, str]:
        return installed_versions("torch")

    def probe(self, target: str, precision: str) -> str | None:
        if missing := missing_torch():
            return missing
        return None if target == "cpu" else "; ".join(cuda_reasons(precision)) or None

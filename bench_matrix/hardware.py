"""What accelerators this machine has, read without importing any framework (nvidia-smi, /proc)."""

from __future__ import annotations

import re
import shutil
import subprocess
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path

# The lowest compute capability each precision needs on an NVIDIA GPU: fp16 arithmetic (Pascal sm_60 runs it,
# Volta sm_70 on tensor cores), bf16 (Ampere sm_80), int8 inference (sm_61, DP4A).
MIN_CAPABILITY = {"fp16": (6, 0), "bf16": (8, 0), "int8": (6, 1)}
CSV_OUTPUT = "--format=csv,noheader,nounits"  # nvidia-smi queries: values only, no header, no units


@dataclass(frozen=True)
class Gpu:
    """One NVIDIA GPU as the driver reports it."""

    name: str
    driver: str
    memory_mib: int | None
    capability: tuple[int, int] | None  # compute capability, e.g. (9, 0) for an H100

    def describe(self) -> str:
        cc = f", compute capability {self.capability[0]}.{self.capability[1]}" if self.capability else ""
        return f"{self.name} (driver {self.driver}{cc})"


def nvidia_smi(*args: str) -> str | None:
    """What `nvidia-smi ARGS` prints, or None without the tool, when it fails or takes over 20 s."""
    smi = shutil.which("nvidia-smi")
    if not smi:
        return None
    try:
        out = subprocess.run([smi, *args], capture_output=True, text=True, timeout=20, check=False)
    except (OSError, subprocess.TimeoutExpired):
        return None
    return out.stdout if out.returncode == 0 else None


def parse_gpus(csv: str) -> tuple[Gpu, ...]:
    """GPUs from `nvidia-smi --query-gpu=name,driver_version,memory.total,compute_cap --format=csv,noheader,nounits`
    (older drivers print '[N/A]' or fail on compute_cap: capability None)."""
    gpus = []
    for line in csv.splitlines():
        parts = [p.strip() for p in line.split(",")]
        if len(parts) < 2 or not parts[0]:
            continue
        memory = int(float(parts[2])) if len(parts) > 2 and re.fullmatch(r"[\d.]+", parts[2]) else None
        cap = re.fullmatch(r"(\d+)\.(\d+)", parts[3]) if len(parts) > 3 else None
        gpus.append(Gpu(parts[0], parts[1], memory, (int(cap[1]), int(cap[2])) if cap else None))
    return tuple(gpus)


@lru_cache(maxsize=1)
def gpus() -> tuple[Gpu, ...]:
    """The NVIDIA GPUs the driver reports (empty when there is no GPU or no driver)."""
    out = nvidia_smi("--query-gpu=name,driver_version,memory.total,compute_cap", CSV_OUTPUT)
    if out is None:  # drivers before 510 do not know compute_cap
        out = nvidia_smi("--query-gpu=name,driver_version,memory.total", CSV_OUTPUT)
    if out is not None:
        return parse_gpus(out)
    proc = Path("/proc/driver/nvidia/gpus")
    return tuple(Gpu(p.name, "unknown", None, None) for p in proc.iterdir()) if proc.is_dir() else ()


def nvidia_gpus() -> tuple[str, ...]:
    """One line per GPU, e.g. 'NVIDIA H100 80GB HBM3 (driver 550.54.15, compute capability 9.0)'."""
    return tuple(gpu.describe() for gpu in gpus())


@lru_cache(maxsize=1)
def driver_cuda_version() -> tuple[int, int] | None:
    """The newest CUDA version the installed driver supports (nvidia-smi's 'CUDA Version'), if known."""
    found = re.search(r"CUDA Version:\s*(\d+)\.(\d+)", nvidia_smi() or "")
    return (int(found[1]), int(found[2])) if found else None


def no_gpu_reason() -> str | None:
    """A precise reason when there is no usable NVIDIA GPU, else None."""
    if gpus():
        return None
    if shutil.which("nvidia-smi") or Path("/proc/driver/nvidia").exists():
        return "an NVIDIA driver is installed but it reports no GPU (nvidia-smi lists none)"
    return "no NVIDIA GPU on this machine (no driver: nvidia-smi not found, /proc/driver/nvidia absent)"


def cuda_mismatch_reason(library: str, built_for: str | None) -> str | None:
    """Why `library` built for CUDA `built_for` (e.g. '12.4') cannot run on this driver, or None."""
    driver = driver_cuda_version()
    found = re.match(r"(\d+)\.(\d+)", built_for or "")
    if driver is None or found is None:
        return None
    wanted = (int(found[1]), int(found[2]))
    if wanted[0] > driver[0]:  # minor-version compatibility covers a newer minor within one major
        return (f"{library} is built for CUDA {built_for}, but the NVIDIA driver supports CUDA up to "
                f"{driver[0]}.{driver[1]}: update the driver or install a {library} build for CUDA {driver[0]}")
    return None


def precision_reason(precision: str, what: str | None = None) -> str | None:
    """Why the GPU is too old for `precision` (compute capability below MIN_CAPABILITY), or None."""
    need = MIN_CAPABILITY.get(precision)
    found = [g for g in gpus() if g.capability is not None]
    if need is None or not found or found[0].capability >= need:
        return None
    gpu = found[0]
    return (f"{gpu.name} has compute capability {gpu.capability[0]}.{gpu.capability[1]}; {what or precision} needs "
            f"{need[0]}.{need[1]} or newer")

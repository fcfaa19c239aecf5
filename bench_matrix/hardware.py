"""What accelerators this machine has, read without importing any framework."""

from __future__ import annotations

import shutil
import subprocess
from functools import lru_cache
from pathlib import Path


@lru_cache(maxsize=1)
def nvidia_gpus() -> tuple[str, ...]:
    """Names of the NVIDIA GPUs the driver reports (empty when there is no GPU or no driver)."""
    smi = shutil.which("nvidia-smi")
    if smi:
        try:
            out = subprocess.run([smi, "--query-gpu=name,driver_version,memory.total", "--format=csv,noheader"],
                                 capture_output=True, text=True, timeout=20, check=False)
            if out.returncode == 0:
                return tuple(line.strip() for line in out.stdout.splitlines() if line.strip())
        except (OSError, subprocess.TimeoutExpired):
            pass
    proc = Path("/proc/driver/nvidia/gpus")
    return tuple(p.name for p in proc.iterdir()) if proc.is_dir() else ()


def no_gpu_reason() -> str | None:
    """A precise reason when there is no usable NVIDIA GPU, else None."""
    if nvidia_gpus():
        return None
    if shutil.which("nvidia-smi") or Path("/proc/driver/nvidia").exists():
        return "an NVIDIA driver is installed but it reports no GPU (nvidia-smi lists none)"
    return "no NVIDIA GPU on this machine (no driver: nvidia-smi not found, /proc/driver/nvidia absent)"

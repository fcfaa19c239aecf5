"""GPU memory held by this process, read from the driver (nvidia-smi), the same way for every runtime."""

from __future__ import annotations

import os

from bench_matrix.hardware import CSV_OUTPUT, nvidia_smi


def _query(*args: str) -> str | None:
    """What nvidia-smi prints for the query `args`, as CSV without header or units; None without it."""
    return nvidia_smi(*args, CSV_OUTPUT)


def process_memory_mib(pid: int | None = None) -> float | None:
    """MiB of GPU memory the driver says process `pid` (default: this one) holds, summed over GPUs; None when the
    driver does not list it (no GPU, or a container whose PID namespace hides it)."""
    out = _query("--query-compute-apps=pid,used_memory")
    if out is None:
        return None
    pid = os.getpid() if pid is None else pid
    used = [float(mem) for line in out.splitlines() if "," in line
            for p, mem in [line.split(",", 1)] if p.strip() == str(pid) and mem.strip().isdigit()]
    return sum(used) if used else None


def device_memory_mib() -> float | None:
    """MiB of memory in use on GPU 0 (every process together), or None without a GPU."""
    out = _query("--query-gpu=memory.used")
    lines = [line.strip() for line in (out or "").splitlines() if line.strip()]
    return float(lines[0]) if lines and lines[0].replace(".", "", 1).isdigit() else None


class GpuMemory:
    """A cell's process's peak GPU memory, read after the runs (every runtime here keeps what it reserved); if
    the driver does not list the process, GPU 0's memory in use less that before the model loaded."""

    def __init__(self) -> None:
        self._before = device_memory_mib()

    def peak(self) -> dict[str, float | str | None]:
        own = process_memory_mib()
        if own is not None:
            return {"peak_gpu_mem_mb": own, "gpu_mem_method": "nvidia-smi used_memory of this process"}
        now = device_memory_mib()
        if now is None or self._before is None:
            return {"peak_gpu_mem_mb": None, "gpu_mem_method": "unavailable (nvidia-smi reports no memory use)"}
        return {"peak_gpu_mem_mb": now - self._before,
                "gpu_mem_method": "GPU 0 memory in use after the runs minus before the load (nvidia-smi)"}

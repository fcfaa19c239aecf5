"""GPU description and GPU memory readings from the driver's output (nvidia-smi text), and their reasons."""

from __future__ import annotations

import os

import pytest

from bench_matrix import hardware
from bench_matrix.measure import gpu

H100 = hardware.Gpu("NVIDIA H100 80GB HBM3", "550.54.15", 81559, (9, 0))
T4 = hardware.Gpu("Tesla T4", "535.104.05", 15360, (7, 5))
K80 = hardware.Gpu("Tesla K80", "470.82.01", 11441, (3, 7))


def test_parse_gpus_reads_capability_and_tolerates_old_drivers() -> None:
    gpus = hardware.parse_gpus("NVIDIA H100 80GB HBM3, 550.54.15, 81559, 9.0\nTesla K80, 470.82.01, 11441, [N/A]\n")
    assert gpus == (H100, hardware.Gpu("Tesla K80", "470.82.01", 11441, None))
    assert H100.describe() == "NVIDIA H100 80GB HBM3 (driver 550.54.15, compute capability 9.0)"


@pytest.mark.parametrize(("gpus", "precision", "expected"), [
    ((H100,), "bf16", None),
    ((T4,), "bf16", "Tesla T4 has compute capability 7.5; bf16 needs 8.0 or newer"),
    ((T4,), "fp16", None),
    ((K80,), "fp16", "Tesla K80 has compute capability 3.7; fp16 needs 6.0 or newer"),
    ((K80,), "int8", "Tesla K80 has compute capability 3.7; int8 needs 6.1 or newer"),
    ((K80,), "fp32", None),
    ((), "bf16", None),  # no GPU: that is no_gpu_reason's to say
])
def test_precision_reason(monkeypatch: pytest.MonkeyPatch, gpus: tuple, precision: str, expected: str | None) -> None:
    monkeypatch.setattr(hardware, "gpus", lambda: gpus)
    assert hardware.precision_reason(precision) == expected


def test_cuda_mismatch_reason(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(hardware, "driver_cuda_version", lambda: (11, 8))
    reason = hardware.cuda_mismatch_reason("torch", "12.4")
    assert reason is not None and "built for CUDA 12.4" in reason and "up to 11.8" in reason
    assert hardware.cuda_mismatch_reason("torch", "11.7") is None  # same major: minor-version compatibility
    assert hardware.cuda_mismatch_reason("torch", None) is None  # a CPU build is another reason
    monkeypatch.setattr(hardware, "driver_cuda_version", lambda: None)
    assert hardware.cuda_mismatch_reason("torch", "12.4") is None  # no driver: no_gpu_reason says it


def test_no_gpu_here_is_said_precisely() -> None:
    if hardware.gpus():
        pytest.skip("this machine has a GPU")
    assert hardware.no_gpu_reason().startswith(("no NVIDIA GPU on this machine", "an NVIDIA driver is installed"))
    assert gpu.GpuMemory().peak() == {"peak_gpu_mem_mb": None,
                                      "gpu_mem_method": "unavailable (nvidia-smi reports no memory use)"}


def test_gpu_memory_reads_this_process_or_falls_back_to_the_device(monkeypatch: pytest.MonkeyPatch) -> None:
    apps = f"4242, 900\n{os.getpid()}, 612\n"
    answers = {"--query-compute-apps=pid,used_memory": apps, "--query-gpu=memory.used": "1500\n"}
    monkeypatch.setattr(gpu, "_query", lambda *args: answers[args[0]])
    memory = gpu.GpuMemory()
    assert memory.peak() == {"peak_gpu_mem_mb": 612.0, "gpu_mem_method": "nvidia-smi used_memory of this process"}
    answers["--query-compute-apps=pid,used_memory"] = "4242, 900\n"  # a container hides our PID
    answers["--query-gpu=memory.used"] = "2100\n"
    peak = memory.peak()
    assert peak["peak_gpu_mem_mb"] == 600.0 and "minus before the load" in peak["gpu_mem_method"]

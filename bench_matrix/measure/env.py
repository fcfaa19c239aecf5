"""The environment a result was measured in: host, CPU (architecture, features, emulation), cores, frequency
policy, memory, GPUs, Python and library versions."""

from __future__ import annotations

import os
import platform
import sys
from importlib.metadata import PackageNotFoundError, version

from bench_matrix import __version__
from bench_matrix.hardware import nvidia_gpus
from bench_matrix.measure.affinity import allowed_cpus, cpu_frequency_state
from bench_matrix.measure.cpu import cpu_facts
from bench_matrix.measure.jetson import jetson_state

# Known libraries recorded with every result and in every cell's fingerprint (a backend lists its own in
# versions())
LIBRARIES = ("numpy", "torch", "onnx", "onnxruntime", "onnxruntime-gpu", "tensorflow", "tensorflow-cpu",
             "tf-keras", "tensorflow-model-optimization", "ai-edge-litert", "tf2onnx", "tensorrt",
             "torch-tensorrt")


def memory_gb() -> float | None:
    try:
        pages, size = os.sysconf("SC_PHYS_PAGES"), os.sysconf("SC_PAGE_SIZE")
        return round(pages * size / 2**30, 1)
    except (ValueError, OSError):
        return None


def available_memory_mb() -> float:
    """Memory available to new processes (MemAvailable of /proc/meminfo; else the physical memory), in MiB."""
    try:
        with open("/proc/meminfo") as meminfo:
            for line in meminfo:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) / 1024
    except OSError:
        pass
    return (memory_gb() or 4.0) * 1024


def installed_versions(*distributions: str) -> dict[str, str]:
    """Versions of those `distributions` that are installed, read from their metadata (nothing imported)."""
    found = {}
    for name in distributions:
        try:
            found[name] = version(name)
        except PackageNotFoundError:
            continue
    return found


def library_versions() -> dict[str, str]:
    return installed_versions(*LIBRARIES)


def host_name() -> str:
    """The name results are stored under: $BENCH_MATRIX_HOST (containers, CI runners), else the network name."""
    return os.environ.get("BENCH_MATRIX_HOST", "").strip() or platform.node() or "unknown"


def run_versions() -> dict[str, str]:
    """The tool's, Python's and the libraries' versions, recorded with each run."""
    return {"bench_matrix": __version__, "python": sys.version.split()[0], **library_versions()}


def capture() -> dict[str, object]:
    """A snapshot recorded with every result: the CPU's model, architecture and features that matter, whether
    it is emulated (qemu-user: its timings are not the board's), and on a Jetson its power mode and clocks."""
    facts = {
        "host": host_name(), "os": f"{platform.system()} {platform.release()}", **cpu_facts(),
        "cores": os.cpu_count(), "cores_usable": len(allowed_cpus()), "cpu_frequency": cpu_frequency_state(),
        "memory_gb": memory_gb(), "gpus": list(nvidia_gpus()), "python": sys.version.split()[0],
        "libraries": library_versions(), "bench_matrix": __version__,
    }
    jetson = jetson_state()
    return {**facts, "jetson": jetson} if jetson else facts

"""CPU placement of the measuring process: pin it to `threads` CPUs, and read the CPU frequency policy."""

from __future__ import annotations

import os
from functools import lru_cache
from itertools import zip_longest
from pathlib import Path

SYSFS_CPU = Path("/sys/devices/system/cpu")
NOT_EXPOSED = "not exposed"


@lru_cache(maxsize=1)
def allowed_cpus() -> tuple[int, ...]:
    """The CPUs this process may run on, as first asked (before `pin_threads` narrowed them)."""
    return tuple(sorted(os.sched_getaffinity(0)))


def pin_threads(threads: int) -> list[int]:
    """Pin every thread of this process (and those it starts later) to `threads` of its allowed CPUs: one per
    physical core, highest-numbered first (CPU 0 often serves more interrupts); all of them if too few."""
    if threads < 1:
        raise ValueError(f"threads must be at least 1, got {threads}")
    allowed = allowed_cpus()
    chosen = sorted(spread(allowed, {cpu: _core_of(cpu) for cpu in allowed})[:threads])
    for task in os.listdir("/proc/self/task"):  # threads already running (e.g. a BLAS pool) too
        try:
            os.sched_setaffinity(int(task), chosen)
        except ProcessLookupError:  # the thread ended meanwhile
            continue
    return chosen


def spread(cpus: tuple[int, ...], core_of: dict[int, tuple[int, int]]) -> list[int]:
    """`cpus` in pinning order: the highest CPU of each physical core (highest core first), then their
    second SMT siblings, and so on, so `threads` CPUs never share a core while a free one is left."""
    by_core: dict[tuple[int, int], list[int]] = {}
    for cpu in sorted(cpus, reverse=True):
        by_core.setdefault(core_of[cpu], []).append(cpu)
    return [cpu for siblings in zip_longest(*by_core.values()) for cpu in siblings if cpu is not None]


def _core_of(cpu: int, root: Path = SYSFS_CPU) -> tuple[int, int]:
    """(package, core) of a CPU from sysfs; a CPU without topology counts as its own core."""
    topology = root / f"cpu{cpu}" / "topology"
    try:
        return (int((topology / "physical_package_id").read_text()), int((topology / "core_id").read_text()))
    except (OSError, ValueError):
        return (-1, cpu)


def cpu_frequency_state(root: Path = SYSFS_CPU) -> dict[str, object]:
    """The frequency policy where sysfs exposes it: scaling driver, governor per CPU, boost (cpufreq/boost,
    1 = on) and Intel turbo (intel_pstate/no_turbo, 1 = off); "not exposed" where it does not."""
    governors = {cpu.name[3:]: _read(cpu / "cpufreq" / "scaling_governor") for cpu in _cpu_dirs(root)}
    exposed = any(value != NOT_EXPOSED for value in governors.values())
    drivers = {_read(cpu / "cpufreq" / "scaling_driver") for cpu in _cpu_dirs(root)} - {NOT_EXPOSED}
    return {"scaling_driver": " / ".join(sorted(drivers)) or NOT_EXPOSED,
            "scaling_governor": governors if exposed else NOT_EXPOSED,
            "boost": _read(root / "cpufreq" / "boost"),
            "intel_no_turbo": _read(root / "intel_pstate" / "no_turbo")}


def _cpu_dirs(root: Path) -> list[Path]:
    """cpu0, cpu1, ... in numeric order."""
    try:
        found = [p for p in root.iterdir() if p.name[:3] == "cpu" and p.name[3:].isdigit()]
    except OSError:
        return []
    return sorted(found, key=lambda p: int(p.name[3:]))


def _read(path: Path) -> str:
    try:
        return path.read_text().strip() or NOT_EXPOSED
    except OSError:
        return NOT_EXPOSED

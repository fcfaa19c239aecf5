"""An NVIDIA Jetson's power mode (`nvpmodel -q`) and clocks, which every record measured on one carries."""

from __future__ import annotations

import shutil
import subprocess
from pathlib import Path

CPU_CLOCKS = Path("/sys/devices/system/cpu")
DEVFREQ = Path("/sys/class/devfreq")  # the GPU's (and the memory controller's) clocks on a Jetson


def jetson_state() -> dict[str, object] | None:
    """The power mode and current clocks (kHz for CPUs, Hz for devfreq devices); None off a Jetson."""
    if shutil.which("nvpmodel") is None:
        return None
    try:
        mode = subprocess.run(["nvpmodel", "-q"], capture_output=True, text=True, timeout=10).stdout
    except (OSError, subprocess.TimeoutExpired) as exc:
        mode = f"nvpmodel -q failed: {exc}"
    return {"nvpmodel": " ".join(mode.split()), "clocks": _clocks()}


def _clocks() -> dict[str, str]:
    found = {f.parent.parent.name: f for f in CPU_CLOCKS.glob("cpu[0-9]*/cpufreq/scaling_cur_freq")}
    found.update({f.parent.name: f for f in DEVFREQ.glob("*/cur_freq")})
    return {name: _read(path) for name, path in sorted(found.items())}


def _read(path: Path) -> str:
    try:
        return path.read_text().strip()
    except OSError:
        return "unreadable"

"""The CPU a result was measured on: its model, architecture, the features that decide what it computes fast
(fp16, int8 dot products, SVE, bf16 on ARM; AVX2, AVX-512, VNNI, AMX on x86) and whether it is emulated."""

from __future__ import annotations

import platform
import struct
from dataclasses import dataclass
from pathlib import Path

CPUINFO = Path("/proc/cpuinfo")
KERNEL_ARCH = Path("/proc/sys/kernel/arch")  # the kernel's architecture, which qemu-user does not translate
AUXV = Path("/proc/self/auxv")  # qemu-user answers it with the emulated CPU's hardware capabilities
ARM = ("aarch64", "arm64")
X86 = ("x86_64", "amd64", "i386", "i686")
# The features that decide what a CPU computes fast, as /proc/cpuinfo spells them, and what each means
ARM_FEATURES = {"asimdhp": "fp16", "asimddp": "int8 dot product", "i8mm": "int8 matrix multiply",
                "bf16": "bf16", "sve": "SVE", "sve2": "SVE2"}
X86_FEATURES = {"avx2": "AVX2", "avx512f": "AVX-512", "avx512_vnni": "AVX-512 VNNI", "avx_vnni": "AVX-VNNI",
                "avx512_bf16": "AVX-512 bf16", "avx512_fp16": "AVX-512 fp16", "amx_bf16": "AMX bf16",
                "amx_int8": "AMX int8"}
# Bits of AT_HWCAP (16) and AT_HWCAP2 (26) on arm64 (Linux's arch/arm64/include/uapi/asm/hwcap.h)
HWCAP_BITS = {16: {9: "fphp", 10: "asimdhp", 20: "asimddp", 22: "sve"},
              26: {1: "sve2", 13: "i8mm", 14: "bf16"}}
# Arm's own cores by their MIDR part number (CPU implementer 0x41): what /proc/cpuinfo on ARM does not name
ARM_CORES = {"0xd03": "Cortex-A53", "0xd04": "Cortex-A35", "0xd05": "Cortex-A55", "0xd07": "Cortex-A57",
             "0xd08": "Cortex-A72", "0xd09": "Cortex-A73", "0xd0a": "Cortex-A75", "0xd0b": "Cortex-A76",
             "0xd0c": "Neoverse-N1", "0xd0d": "Cortex-A77", "0xd40": "Neoverse-V1", "0xd41": "Cortex-A78",
             "0xd42": "Cortex-A78AE", "0xd44": "Cortex-X1", "0xd46": "Cortex-A510", "0xd47": "Cortex-A710",
             "0xd49": "Neoverse-N2", "0xd4f": "Neoverse-V2"}


@dataclass(frozen=True)
class Cpu:
    """A CPU as /proc/cpuinfo describes it (on ARM, its board's model line where the kernel adds one)."""

    arch: str  # "aarch64", "x86_64", or what uname says
    model: str
    flags: frozenset[str]  # every feature flag, as the kernel spells it

    @property
    def features(self) -> tuple[str, ...]:
        """The features that matter for inference, named (e.g. 'fp16', 'int8 dot product', 'AVX-512 VNNI')."""
        known = ARM_FEATURES if self.arch in ARM else X86_FEATURES
        return tuple(name for flag, name in known.items() if flag in self.flags)

    def lacks(self) -> tuple[str, ...]:
        """The features that matter which this CPU does not have, named."""
        known = ARM_FEATURES if self.arch in ARM else X86_FEATURES
        return tuple(name for flag, name in known.items() if flag not in self.flags)


def parse_cpuinfo(text: str, machine: str) -> Cpu:
    """The CPU that a /proc/cpuinfo text describes, read by a `machine` ('aarch64', 'x86_64') process."""
    fields: dict[str, str] = {}
    for line in text.splitlines():
        key, sep, value = line.partition(":")
        if sep and key.strip() not in fields:
            fields[key.strip()] = value.strip()
    flags = frozenset((fields.get("Features") or fields.get("flags") or "").split())
    arch = _arch(fields, machine)
    return Cpu(arch, _model(fields) or machine, flags)


def _arch(fields: dict[str, str], machine: str) -> str:
    """The architecture a /proc/cpuinfo text is of: ARM's names 'Features', x86's 'vendor_id' and 'flags'."""
    if "CPU implementer" in fields or "Features" in fields:
        return machine if _family(machine) == "arm" else "aarch64"
    if "vendor_id" in fields and "flags" in fields:
        return machine if _family(machine) == "x86" else "x86_64"
    return machine


def _model(fields: dict[str, str]) -> str:
    """'model name' on x86 (and some ARM kernels); on ARM the core by its part number, and the board."""
    core = fields.get("model name", "")
    if fields.get("CPU implementer") == "0x41":
        core = ARM_CORES.get(fields.get("CPU part", ""), f"Arm core {fields.get('CPU part', '?')}")
    elif "CPU implementer" in fields and not core:
        core = f"implementer {fields['CPU implementer']} part {fields.get('CPU part', '?')}"
    board = fields.get("Model", "")
    return f"{core} ({board})" if core and board else core or board


def hwcap_flags(auxv: bytes) -> frozenset[str]:
    """The arm64 feature flags that an auxiliary vector's AT_HWCAP and AT_HWCAP2 set."""
    found = set()
    for offset in range(0, len(auxv) - 15, 16):
        key, value = struct.unpack_from("<QQ", auxv, offset)
        found |= {flag for bit, flag in HWCAP_BITS.get(key, {}).items() if value >> bit & 1}
    return frozenset(found)


def emulation(machine: str, kernel_arch: str | None, cpuinfo_arch: str) -> str | None:
    """Why this process runs emulated (an arm64 program on an x86_64 kernel, through qemu-user), or None."""
    if kernel_arch and _family(kernel_arch) != _family(machine):
        return (f"emulated: {machine} programs run by qemu-user on an {kernel_arch} kernel; timings are not "
                "the board's")
    if _family(cpuinfo_arch) != _family(machine):
        return f"emulated: {machine} programs on a CPU that /proc/cpuinfo describes as {cpuinfo_arch}"
    return None


def _family(arch: str) -> str:
    """'arm' for arm64 and 32-bit ARM, 'x86' for x86_64 and i686: a 32-bit userland is not an emulation."""
    return "arm" if arch.startswith(("arm", "aarch")) else "x86" if arch in X86 else arch


def _read(path: Path, binary: bool = False) -> str | bytes:
    try:
        return path.read_bytes() if binary else path.read_text().strip()
    except OSError:
        return b"" if binary else ""


def this_cpu() -> tuple[Cpu, str | None]:
    """This machine's CPU as this process sees it, and why it is emulated (None on real hardware); emulated,
    its features come from the auxiliary vector (/proc/cpuinfo is the host's, or written for the board)."""
    machine = platform.machine()
    cpu = parse_cpuinfo(str(_read(CPUINFO)), machine)
    emulated = emulation(machine, str(_read(KERNEL_ARCH)) or None, cpu.arch)
    if emulated and machine in ARM:
        model = f"{cpu.model} (qemu)" if cpu.arch == machine else f"qemu {machine} CPU on {cpu.model}"
        cpu = Cpu(machine, model, hwcap_flags(bytes(_read(AUXV, binary=True))))
    return cpu, emulated


def cpu_facts() -> dict[str, object]:
    """What a record says of its CPU: the model, architecture, features that matter, and emulation."""
    cpu, emulated = this_cpu()
    facts: dict[str, object] = {"cpu": cpu.model, "arch": cpu.arch, "cpu_features": list(cpu.features)}
    return {**facts, "emulated": emulated} if emulated else facts

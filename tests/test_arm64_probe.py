"""What a device says of its CPU, from recorded /proc/cpuinfo files of real boards (where each comes from:
tests/data/cpuinfo/README.md), and whether it runs emulated."""

from __future__ import annotations

import platform
import struct
from pathlib import Path

from bench_matrix.measure.cpu import X86_FEATURES, emulation, hwcap_flags, parse_cpuinfo, this_cpu
from bench_matrix.measure.env import capture

CPUINFO = Path(__file__).parent / "data" / "cpuinfo"
QEMU = "emulated: aarch64 programs run by qemu-user on an x86_64 kernel; timings are not the board's"


def _board(name: str):
    return parse_cpuinfo((CPUINFO / name).read_text(), "aarch64")


def test_a_raspberry_pi_4_has_neither_fp16_arithmetic_nor_int8_dot_products() -> None:
    pi4 = _board("raspberry-pi-4.txt")
    assert (pi4.arch, pi4.model) == ("aarch64", "Cortex-A72 (Raspberry Pi 4 Model B Rev 1.1)")
    assert pi4.features == ()
    assert {"fp16", "int8 dot product", "SVE"} <= set(pi4.lacks())


def test_a_raspberry_pi_5_and_a_jetson_orin_compute_fp16_and_int8_dot_products_without_sve() -> None:
    pi5, orin = _board("raspberry-pi-5.txt"), _board("jetson-agx-orin.txt")
    assert pi5.model == "Cortex-A76 (Raspberry Pi 5 Model B Rev 1.0)"
    assert orin.model == "Cortex-A78AE"  # Jetson kernels add no board line
    for board in (pi5, orin):
        assert board.features == ("fp16", "int8 dot product")
        assert {"SVE", "bf16", "int8 matrix multiply"} <= set(board.lacks())


def test_an_arm64_program_reading_an_x86_cpuinfo_is_emulated_and_takes_its_features_from_hwcaps() -> None:
    host = "processor\t: 0\nvendor_id\t: AuthenticAMD\nmodel name\t: AMD EPYC\nflags\t\t: fpu avx2 avx512f\n"
    seen = parse_cpuinfo(host, "aarch64")
    assert seen.arch == "x86_64"  # /proc/cpuinfo is the host's under qemu-user
    assert emulation("aarch64", "x86_64", seen.arch) == QEMU
    assert emulation("aarch64", None, seen.arch).startswith("emulated: aarch64 programs on a CPU that")
    # AT_HWCAP (16): fphp, asimdhp, asimddp, sve; AT_HWCAP2 (26): bf16; then AT_NULL
    auxv = struct.pack("<6Q", 16, 1 << 9 | 1 << 10 | 1 << 20 | 1 << 22, 26, 1 << 14, 0, 0)
    assert hwcap_flags(auxv) == {"fphp", "asimdhp", "asimddp", "sve", "bf16"}


def test_a_real_board_or_a_32_bit_userland_on_an_arm64_kernel_is_not_emulated() -> None:
    assert emulation("aarch64", "aarch64", "aarch64") is None
    assert emulation("armv7l", "aarch64", "aarch64") is None
    assert emulation("x86_64", "x86_64", "x86_64") is None


def test_records_say_this_machines_architecture_and_features_as_its_probe_reads_them() -> None:
    cpu, emulated = this_cpu()
    env = capture()
    assert env["arch"] == cpu.arch and env["cpu_features"] == list(cpu.features)
    assert env.get("emulated") == emulated
    if emulated is None and cpu.arch == platform.machine() == "x86_64":
        assert set(cpu.features) <= set(X86_FEATURES.values())

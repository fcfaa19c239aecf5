"""What a device says of its CPU, from recorded /proc/cpuinfo files of real boards (where each comes from:
tests/data/cpuinfo/README.md), and how an emulated device's timings are marked in reports and `compare`."""

from __future__ import annotations

import platform
import struct
from pathlib import Path

import numpy as np

from bench_matrix.cell import Cell
from bench_matrix.measure.cpu import X86_FEATURES, emulation, hwcap_flags, parse_cpuinfo, this_cpu
from bench_matrix.measure.env import capture
from bench_matrix.report.analysis.compare import compare
from bench_matrix.report.analysis.metric_change import Side
from bench_matrix.report.analysis.recommend import Recommendation
from bench_matrix.report.analysis.summary import summarize
from bench_matrix.report.render.markdown import index_page, model_page
from bench_matrix.report.render.verdict_view import _objective
from bench_matrix.store import CellRecord

CPUINFO = Path(__file__).parent / "data" / "cpuinfo"
QEMU = "emulated: aarch64 programs run by qemu-user on an x86_64 kernel; timings are not the board's"
BASE = Cell("pilotnet", "pytorch", "pytorch", "none", "fp32", "cpu")
INT8 = Cell("pilotnet", "pytorch", "onnxruntime", "ptq_static", "int8", "cpu")


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
    # recorded on the emulated board (QEMU_CPU=cortex-a76): a Raspberry Pi 5's core, fp16 and dot product only
    assert hwcap_flags((CPUINFO / "qemu-cortex-a76.auxv").read_bytes()) == {"fphp", "asimdhp", "asimddp"}


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


def _record(cell: Cell, p50: float, mse: float, env: dict) -> CellRecord:
    metrics = {"size_bytes": 1_000_000, "mse": mse, "throughput_sps": 1000 / p50,
               "latency_ms": {"p50": p50, "p90": p50, "p99": p50 * 2, "n": 200}}
    return CellRecord(cell=cell, status="ok", metrics=metrics, env=env, run_id=1)


X86 = {"host": "workstation", "cpu": "AMD EPYC", "arch": "x86_64", "cpu_features": ["AVX2"]}
ARM = {"host": "arm64-qemu", "cpu": "qemu aarch64 CPU on AMD EPYC", "arch": "aarch64",
       "cpu_features": ["fp16", "int8 dot product", "SVE"], "emulated": QEMU}


def test_the_report_marks_every_timing_of_an_emulated_device_and_says_why(tmp_path: Path) -> None:
    records = [_record(BASE, 40.0, 0.010, ARM), _record(INT8, 9.0, 0.013, ARM)]
    report = summarize(records, {}, {})
    assert "| 9.00 (emu) |" in index_page(report)  # the fastest cell's p50
    recommended = Recommendation("pilotnet", "cpu", None, "p50", 1, 2, best=records[1])
    assert _objective(recommended) == "p50 9.00 (emu) ms"  # the Verdict's objective
    (model,) = report.models
    page = model_page(model, (), tmp_path)
    assert "40.0 (emu)" in page and "9.00 (emu)" in page
    assert "Timings marked (emu), 2 of 2 cells, come from an emulated device" in page
    assert "not how fast the board is" in page and f"**Emulated**: {QEMU}" in page
    assert "**Architecture**: aarch64" in page and "**CPU features**: fp16, int8 dot product, SVE" in page
    plain = model_page(summarize([_record(BASE, 40.0, 0.010, X86)], {}, {}).models[0], (), tmp_path)
    assert "(emu)" not in plain.replace('"(emu)"', "") and "Emulated" not in plain


def test_compare_of_x86_and_emulated_arm64_judges_accuracy_per_cell_never_timings() -> None:
    samples = {cell.key: np.full(200, 1.0) for cell in (BASE, INT8)}
    x86 = Side("x86", [_record(BASE, 1.0, 0.010, X86), _record(INT8, 0.5, 0.0100, X86)], samples, {})
    arm = Side("arm64", [_record(BASE, 40.0, 0.010, ARM), _record(INT8, 9.0, 0.0130, ARM)], samples, {})
    result = compare(x86, arm)
    by_key = {cell.key: cell for cell in result.cells}
    for cell in by_key.values():
        timed = [m for m in cell.metrics if m.metric in ("p50", "p99", "throughput")]
        assert [m.verdict for m in timed] == ["not comparable"] * 3
        assert {m.why for m in timed} == {"timed on an emulated device in new: not the board's speed"}
    accuracy = {key: next(m for m in cell.metrics if m.metric == "accuracy") for key, cell in by_key.items()}
    assert accuracy[BASE.key].verdict == "unchanged"
    assert accuracy[INT8.key].verdict == "worse" and round(accuracy[INT8.key].change, 9) == 0.3
    assert result.regressions == [(INT8.key, "accuracy")]


def test_a_device_is_asked_whether_it_can_run_a_cell_not_whether_it_could_convert_it(tmp_path, monkeypatch):
    """A Raspberry Pi with LiteRT and no TensorFlow runs .tflite files converted here: its probe
    (measure_only) must not skip them for the TensorFlow converter it lacks, while this machine's own probe
    does."""
    from bench_matrix.jobs import ProbeJob
    from bench_matrix.jobs.probe import probe
    from bench_matrix.workspace import Workspace

    _hidden(monkeypatch, "tensorflow")
    key = ("tflite", "tensorflow", "none", "fp32", "cpu", "keras", "{}", "")
    here = probe(ProbeJob(Workspace(tmp_path), ("tflite",), (key,)))
    there = probe(ProbeJob(Workspace(tmp_path), ("tflite",), (key,), measure_only=True))
    assert "TensorFlow is not installed" in (here.rulings[key].skip or "")
    assert there.rulings[key].skip is None


def _hidden(monkeypatch, *modules: str) -> None:
    """`modules` cannot be found (as on a board that lacks them), without uninstalling anything."""
    import importlib.util

    find_spec = importlib.util.find_spec
    monkeypatch.setattr(importlib.util, "find_spec", lambda name, *a: None if name in modules
                        else find_spec(name, *a))


def test_a_device_without_torch_skips_every_torch_backend_naming_it(monkeypatch) -> None:
    """Seen on the emulated board: `pytorch: cpu: ready` without torch, and its GPU probes crashing with
    ModuleNotFoundError."""
    from bench_matrix_backends.pytorch import PyTorchBackend
    from bench_matrix_backends.torch_compile import AotInductorBackend, TorchCompileBackend
    from bench_matrix_backends.torch_tensorrt import TorchTensorRTBackend
    from bench_matrix_backends.torchscript import TorchScriptBackend

    _hidden(monkeypatch, "torch")
    for backend in (PyTorchBackend(), TorchScriptBackend(), TorchCompileBackend(), AotInductorBackend(),
                    TorchTensorRTBackend()):
        for target in sorted({t for support in backend.supports for t in support.targets}):
            assert (backend.probe(target, "fp32") or "").startswith("torch is not installed"), backend.name


def test_openvino_runs_its_ir_without_onnx_which_only_converting_needs(monkeypatch) -> None:
    """Seen on the emulated board: every openvino cell skipped for onnx, which only the conversion here
    uses."""
    from bench_matrix_backends.openvino import OpenVinoBackend

    _hidden(monkeypatch, "onnx")
    backend = OpenVinoBackend()
    assert backend.probe("cpu", "fp32") is None
    assert (backend.probe_source("pytorch", "state_dict") or "").startswith("onnx is not installed")


def test_device_check_shows_a_boards_core_features_and_what_it_lacks(capsys) -> None:
    """`device check`'s environment rows for a Raspberry Pi 5 (its recorded cpuinfo) and for the same core
    emulated."""
    from rich.console import Console

    from bench_matrix import __version__
    from bench_matrix.cli_device import _show_environment

    pi5 = _board("raspberry-pi-5.txt")
    env = {"os": "Linux 6.6.51+rpt-rpi-2712", "cpu": pi5.model, "arch": pi5.arch,
           "cpu_features": list(pi5.features), "cores": 4, "memory_gb": 7.9, "gpus": []}
    hello = {"python": "3.11.2", "bench_matrix": __version__, "env": env}
    _show_environment(Console(width=200), hello, "/home/pi/bm/bin/python")
    shown = capsys.readouterr().out
    assert "  cpu          Cortex-A76 (Raspberry Pi 5 Model B Rev 1.0), 4 cores, 7.9 GB memory\n" in shown
    assert "  arch         aarch64\n" in shown and "emulated" not in shown
    assert "  cpu features fp16, int8 dot product (not: int8 matrix multiply, bf16, SVE, SVE2)\n" in shown
    _show_environment(Console(width=200), {**hello, "env": {**env, "emulated": QEMU}}, "python3")
    assert f"  emulated     {QEMU}\n" in capsys.readouterr().out

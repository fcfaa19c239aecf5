"""The emulated arm64 board end to end (opt-in: `pytest -m arm64`, with `benchmarks/arm64_device.sh start` run
first, as root): `device check`, a two-cell run measured there, the records' host, architecture and emulated
flag, and `compare` of the same cells measured here and there. About 3 minutes on our 2-core machine."""

from __future__ import annotations

import json
import os
import sqlite3
import subprocess
from pathlib import Path

import pytest
from conftest import cli, onnx_matrix_text

BOARD = Path(os.environ.get("BM_ARM64", Path.home() / ".cache" / "bench-matrix" / "arm64"))
SSH_CONFIG = BOARD / "ssh_config"
DEVICE = "arm64-qemu=/opt/bm/bin/python"
TWO_CELLS = onnx_matrix_text(["tiny"], ["fp32", "int8"]).replace("strategy: [none]",
                                                                  "strategy: [none, ptq_static]")
pytestmark = pytest.mark.arm64


@pytest.fixture(scope="module")
def board() -> list[str]:
    """The options naming the running board; skipped with what to do where it is not running."""
    reachable = SSH_CONFIG.is_file() and subprocess.run(
        ["ssh", "-F", str(SSH_CONFIG), "-o", "BatchMode=yes", "arm64-qemu", "true"], capture_output=True,
        timeout=60).returncode == 0
    if not reachable:
        pytest.skip(f"the emulated arm64 board is not running ({SSH_CONFIG}): benchmarks/arm64_device.sh "
                    "build, then start (as root)")
    return ["--device", DEVICE, "--ssh-config", str(SSH_CONFIG)]


def test_device_check_reports_aarch64_its_features_and_that_it_is_emulated(tmp_path: Path, board) -> None:
    out = cli(tmp_path, "device", "check", DEVICE, "--ssh-config", str(SSH_CONFIG), timeout=600)
    assert out.returncode == 0, out.stdout + out.stderr
    rows = {line[2:15].strip(): line[15:] for line in out.stdout.splitlines() if line.startswith("  ")}
    assert rows["arch"] == "aarch64" and rows["cpu"].startswith("Cortex-A76 (qemu)")
    assert rows["cpu features"] == "fp16, int8 dot product (not: int8 matrix multiply, bf16, SVE, SVE2)"
    assert rows["emulated"].startswith("emulated: aarch64 programs run by qemu-user on an x86_64 kernel")
    for ready in ("onnxruntime: cpu: ready", "openvino: cpu: ready for fp32/fp16", "tflite: cpu: ready"):
        assert ready in out.stdout


def _records(db: Path) -> list[dict]:
    with sqlite3.connect(db) as con:
        rows = con.execute("SELECT key, status, host, env FROM records ORDER BY key").fetchall()
    return [{"key": k, "status": s, "host": h, "env": json.loads(e)} for k, s, h, e in rows]


def test_two_cells_measured_there_are_marked_emulated_and_compared_on_accuracy_only(onnx_project, board):
    (onnx_project / "m.yaml").write_text(TWO_CELLS)
    here = cli(onnx_project, "run", "m.yaml", "--results", "x86.sqlite", timeout=600)
    assert here.returncode == 0, here.stdout + here.stderr
    there = cli(onnx_project, "run", "m.yaml", "--results", "arm64.sqlite", "--executor", "ssh", *board,
                timeout=1200)
    assert there.returncode == 0, there.stdout + there.stderr
    records = _records(onnx_project / "arm64.sqlite")
    seen = [(r["status"], r["host"], r["env"]["arch"]) for r in records]
    assert seen == [("ok", "arm64-qemu", "aarch64")] * 2
    assert all(r["env"]["emulated"].startswith("emulated: aarch64 programs") for r in records)
    assert "x86_64" == _records(onnx_project / "x86.sqlite")[0]["env"]["arch"]
    report = cli(onnx_project, "report", "--results", "arm64.sqlite", "--format", "md", "--out", "arm")
    assert report.returncode == 0 and "(emu)" in (onnx_project / "arm" / "tiny.md").read_text()
    compared = cli(onnx_project, "compare", "x86.sqlite", "arm64.sqlite", "--format", "json")
    found = json.loads(compared.stdout)
    for cell in found["cells"]:
        metrics = cell["metrics"]
        assert {metrics[k]["verdict"] for k in ("p50", "p99", "throughput")} == {"not comparable"}
        assert metrics["accuracy"]["verdict"] in ("unchanged", "better", "worse")

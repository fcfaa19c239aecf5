"""A workspace named by a relative path in one run and from elsewhere in the next: cached preparations
must not keep paths that only made sense from the first run's directory (an ONNX model: the paths are
the workspace's, whatever the framework)."""

from __future__ import annotations

import json
import subprocess
import sys

from conftest import onnx_matrix_text


def cli_in(cwd, workspace, *args: str) -> subprocess.CompletedProcess:
    """`bench-matrix --workspace WORKSPACE ARGS...` started in `cwd`."""
    return subprocess.run([sys.executable, "-m", "bench_matrix.cli", "--workspace", str(workspace), *args],
                          cwd=cwd, capture_output=True, text=True, timeout=300)


def test_a_cached_model_is_found_from_another_directory(onnx_project, tmp_path_factory):
    (onnx_project / "m.yaml").write_text(onnx_matrix_text(["tiny", "twin"], ["fp32"]))
    first = cli_in(onnx_project, "ws", "run", "m.yaml")
    assert "2 ok, 0 skipped, 0 failed" in first.stdout, first.stdout + first.stderr
    elsewhere = tmp_path_factory.mktemp("elsewhere")
    second = cli_in(elsewhere, onnx_project / "ws", "run", str(onnx_project / "m.yaml"), "--force")
    assert "2 ok, 0 skipped, 0 failed" in second.stdout, second.stdout + second.stderr
    report = cli_in(elsewhere, onnx_project / "ws", "report", "--format", "json")
    records = json.loads(report.stdout)["records"]
    assert [r["status"] for r in records] == ["ok", "ok"]
    assert all(r["metrics"]["max_abs_diff_vs_baseline"] < 1e-4 for r in records)

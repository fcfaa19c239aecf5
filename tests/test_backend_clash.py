"""A plugin registering a built-in backend's name never silently replaces it: the clash is an error naming
both distributions, unless the plugin's class declares `replaces`; `bench-matrix backends` shows which is in
effect. The plugins are real distributions (a .dist-info with entry points) on sys.path."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

from bench_matrix.registry import BackendLoadError, available, load_backend

TESTS = Path(__file__).resolve().parent


def _install(tmp_path: Path, monkeypatch: pytest.MonkeyPatch, cls: str) -> str:
    """A distribution vendor-ort 0.1 registering `onnxruntime` as plugin_replaces:CLS, on sys.path here and in
    the CLI's; the built-in backend's distribution ("bench-matrix VERSION")."""
    dist = tmp_path / "site" / "vendor_ort-0.1.dist-info"
    dist.mkdir(parents=True)
    (dist / "METADATA").write_text("Metadata-Version: 2.1\nName: vendor-ort\nVersion: 0.1\n")
    (dist / "entry_points.txt").write_text(f"[bench_matrix.backends]\nonnxruntime = plugin_replaces:{cls}\n")
    builtin = available()["onnxruntime"].distribution
    monkeypatch.syspath_prepend(str(tmp_path / "site"))
    monkeypatch.syspath_prepend(str(TESTS))
    monkeypatch.setenv("PYTHONPATH", os.pathsep.join([str(tmp_path / "site"), str(TESTS),
                                                      os.environ.get("PYTHONPATH", "")]))
    return builtin


def _backends(tmp_path: Path) -> str:
    """What `bench-matrix backends` prints about onnxruntime."""
    done = subprocess.run([sys.executable, "-m", "bench_matrix.cli", "--workspace", str(tmp_path / "ws"),
                           "backends"], capture_output=True, text=True, timeout=300,
                          env={**os.environ, "COLUMNS": "300"}, cwd=tmp_path)
    assert done.returncode == 0, done.stderr
    return done.stdout.split("\nonnxruntime ", 1)[1].split("\n\n", 1)[0]


def test_a_plugin_with_a_built_in_backends_name_is_an_error_naming_both(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    builtin = _install(tmp_path, monkeypatch, "ClashesWithOnnxRuntime")
    entry = available()["onnxruntime"]
    said = (f"backend 'onnxruntime' is registered by {builtin} (bench_matrix_backends.onnxruntime:"
            f"OnnxRuntimeBackend) and vendor-ort 0.1 (plugin_replaces:ClashesWithOnnxRuntime), and none of "
            f"their classes declares replaces = 'onnxruntime'")
    assert entry.clash.startswith(said), entry.clash
    with pytest.raises(BackendLoadError, match="registered by .* and vendor-ort 0.1"):
        load_backend("onnxruntime")
    assert f"cannot be loaded: {said}" in " ".join(_backends(tmp_path).split())


def test_a_plugin_that_declares_it_replaces_a_built_in_backend_is_in_effect(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    builtin = _install(tmp_path, monkeypatch, "ReplacesOnnxRuntime")
    entry = available()["onnxruntime"]
    assert (entry.distribution, entry.replaced, entry.clash) == ("vendor-ort 0.1", (builtin,), "")
    assert type(load_backend("onnxruntime")).__name__ == "ReplacesOnnxRuntime"
    shown = " ".join(_backends(tmp_path).split())
    assert shown.startswith("vendor-ort 0.1 · plugin_replaces:ReplacesOnnxRuntime"), shown
    assert f"replaces the onnxruntime of {builtin} (its class declares replaces = 'onnxruntime')" in shown

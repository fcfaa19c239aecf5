"""The plugin API: the built-in backends use bench-matrix only through `bench_matrix.plugin`, which is
exactly what docs/plugins.md documents; targets say their device through the backends; the core names no
runtime."""

from __future__ import annotations

import ast
import re
from pathlib import Path

import pytest

from bench_matrix import plugin
from bench_matrix.registry import available, load_backend

ROOT = Path(__file__).resolve().parents[1]
BUILT_IN = tuple(name for name, entry in available().items() if entry.builtin)
# the libraries recorded with every result: a list of known names, the one place the core may name them
LIBRARY_NAMES = ROOT / "bench_matrix" / "measure" / "env.py"


def _imported(tree: ast.AST) -> list[tuple[int, str]]:
    """(line, module) of every absolute import in a module, at any depth."""
    found = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            found += [(node.lineno, alias.name) for alias in node.names]
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            found.append((node.lineno, node.module))
    return found


@pytest.mark.parametrize("path", sorted((ROOT / "backends").glob("*.py")), ids=lambda p: p.name)
def test_built_in_backends_import_bench_matrix_only_through_the_plugin_api(path: Path) -> None:
    wrong = [f"{path.name}:{line}: {module}" for line, module in _imported(ast.parse(path.read_text()))
             if module.split(".")[0] == "bench_matrix" and module != "bench_matrix.plugin"]
    assert not wrong, f"import these from bench_matrix.plugin instead: {wrong}"


def _documented() -> set[str]:
    """The names the table of docs/plugins.md's "The plugin API" section lists in its first column."""
    text = (ROOT / "docs" / "plugins.md").read_text()
    section = text.split("### The plugin API\n", 1)[1].split("\n### ", 1)[0]
    rows = [line.split(" | ")[0] for line in section.splitlines() if line.startswith("| `")]
    return {re.match(r"\w+", code)[0] for row in rows for code in re.findall(r"`([^`]+)`", row)}


def test_the_plugin_api_is_exactly_what_plugins_md_documents() -> None:
    assert set(plugin.__all__) == _documented()
    assert len(plugin.__all__) == len(set(plugin.__all__))
    assert all(hasattr(plugin, name) for name in plugin.__all__)


def test_built_in_gpu_targets_run_on_cuda_and_every_other_target_on_the_cpu() -> None:
    """The cuda and tensorrt targets time end to end and get a GPU on Ray, as before: now by declaration."""
    for name in BUILT_IN:
        backend = load_backend(name)
        for target in {t for s in backend.supports for t in s.targets}:
            expected = "cuda" if target in ("cuda", "tensorrt") else "cpu"
            assert backend.device(target) == expected, (name, target)


def test_the_core_names_no_runtime_target() -> None:
    """Targets come from the backends: bench_matrix/ names no TensorRT but among the libraries it records."""
    naming = [f"{path.relative_to(ROOT)}:{n}" for path in sorted((ROOT / "bench_matrix").rglob("*.py"))
              if path != LIBRARY_NAMES
              for n, line in enumerate(path.read_text().splitlines(), 1) if "tensorrt" in line.lower()]
    assert not naming


def test_plugins_flatten_outputs_and_bind_inputs_as_the_built_in_backends_do() -> None:
    """docs/plugins.md's rules for outputs (flattened, dicts by sorted key) and for a PyTorch module's inputs
    (positionally, or by name where forward names them in another order) are functions of the plugin API."""
    import torch

    from bench_matrix_backends import _torch, tensorflow

    assert _torch.flat_outputs is plugin.flat_outputs is tensorflow.flat_outputs
    speed, angle, extra = (torch.full((2, 1), float(v)) for v in (1, 2, 3))
    flat = plugin.flat_outputs({"speed": speed, "angle": (angle, None), "b": [extra]})
    assert flat == [angle, extra, speed]

    class Named(torch.nn.Module):
        def forward(self, ids: torch.Tensor, features: torch.Tensor, scale: float = 2.0) -> torch.Tensor:
            return features * scale - ids

    features, ids = torch.ones(2, 3), torch.arange(6.0).reshape(2, 3)
    bound = plugin.for_inputs(Named(), ["features", "ids"])
    assert torch.equal(bound(features, ids), Named()(ids=ids, features=features))

"""The house's layers (docs/README.md, Layers): every import of bench_matrix and the built-in backends, at
module level, in functions and under TYPE_CHECKING, read from the source with ast; none goes up a layer or
round in a circle, and the plugin API loads no more than the plugin contract."""

from __future__ import annotations

import ast
import re
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = {"bench_matrix": ROOT / "bench_matrix", "bench_matrix_backends": ROOT / "backends"}


def modules() -> dict[str, Path]:
    """Every module by its dotted name (a package by its own name)."""
    found = {}
    for package, folder in PACKAGES.items():
        for path in sorted(folder.rglob("*.py")):
            parts = (package, *path.relative_to(folder).with_suffix("").parts)
            found[".".join(parts[:-1] if parts[-1] == "__init__" else parts)] = path
    return found


def imports(name: str, path: Path, known: dict[str, Path]) -> set[str]:
    """The known modules `name` imports anywhere in its source (a name imported from a package counts as its
    module where it is one, else as the package)."""
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    found = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            targets = [alias.name for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                up = package.split(".")[:len(package.split(".")) - (node.level - 1)]
                base = ".".join(up + ([base] if base else []))
            targets = [f"{base}.{a.name}" if f"{base}.{a.name}" in known else base for a in node.names]
        else:
            continue
        for target in targets:
            while target and target not in known:
                target = target.rpartition(".")[0]
            if target and target != name:
                found.add(target)
    return found


def layers() -> dict[str, tuple[int, str]]:
    """docs/README.md's Layers table: each module name (below bench_matrix) -> (floor, layer)."""
    text = (ROOT / "docs" / "README.md").read_text().split("## Layers", 1)[1]
    table = {}
    for floor, layer, names in re.findall(r"^\| (\d+) \| ([^|]+) \| ([^|]+) \|$", text, re.M):
        for module in re.findall(r"`([\w.]+)`", names.split(" (")[0] + names.split(")")[-1]):
            table[module] = (int(floor), layer.strip())
    return table


def floor_of(module: str, table: dict[str, tuple[int, str]]) -> tuple[int, str] | None:
    """The layer of the most specific name in the table that covers `module`."""
    if module == "bench_matrix":
        return table.get("__init__")
    name = module if module.startswith("bench_matrix_backends") else module.removeprefix("bench_matrix.")
    while name:
        if name in table:
            return table[name]
        name = name.rpartition(".")[0]
    return None


GRAPH = {name: imports(name, path, modules()) for name, path in modules().items()}


def test_every_module_has_a_layer():
    table = layers()
    assert table, "docs/README.md has no Layers table"
    assert [name for name in GRAPH if floor_of(name, table) is None] == []


def test_no_import_goes_up_a_layer():
    table = layers()
    upward = [f"{a} ({floor_of(a, table)[1]}) imports {b} ({floor_of(b, table)[1]})"
              for a, targets in GRAPH.items() for b in sorted(targets)
              if floor_of(a, table) and floor_of(b, table) and floor_of(b, table)[0] > floor_of(a, table)[0]]
    assert upward == []


def circles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The import circles: each strongly connected set of more than one module (Tarjan's algorithm)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    found: list[list[str]] = []

    def visit(node: str) -> None:
        index[node] = low[node] = len(index)
        stack.append(node)
        for other in sorted(graph[node]):
            if other not in index:
                visit(other)
                low[node] = min(low[node], low[other])
            elif other in stack:
                low[node] = min(low[node], index[other])
        if low[node] == index[node]:
            members = []
            while not members or members[-1] != node:
                members.append(stack.pop())
            if len(members) > 1:
                found.append(sorted(members))

    sys.setrecursionlimit(max(sys.getrecursionlimit(), 10 * len(graph)))
    for node in sorted(graph):
        if node not in index:
            visit(node)
    return found


def test_no_imports_go_round_in_a_circle():
    assert circles(GRAPH) == []


def test_the_walk_sees_a_circle_and_an_upward_import():
    assert circles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]
    table = layers()
    cell, summary, plots = (floor_of(f"bench_matrix.{name}", table)[0]
                            for name in ("cell", "report.analysis.summary", "report.render.plots"))
    assert cell < summary < plots  # the report's figures sit below what draws them
    assert "bench_matrix.registry" in GRAPH["bench_matrix.report.render.sections"]  # at module level
    assert "bench_matrix.report.render.plots" in GRAPH["bench_matrix.report"]  # in a function
    assert "bench_matrix.jobs" in GRAPH["bench_matrix.scenarios.base"]  # under TYPE_CHECKING


def written(node: ast.AST) -> list[str]:
    """The modules an import statement names, as written (none for any other node)."""
    if isinstance(node, ast.Import):
        return [alias.name for alias in node.names]
    return [node.module or ""] if isinstance(node, ast.ImportFrom) else []


def test_the_report_analysis_draws_nothing():
    """report.analysis computes figures only: it imports no drawing library (and the table keeps
    report.render out of it)."""
    drawing = [f"{name} imports {module}" for name, path in modules().items()
               if name.startswith("bench_matrix.report.analysis")
               for node in ast.walk(ast.parse(path.read_text(), str(path)))
               for module in written(node) if module.split(".")[0] in ("rich", "matplotlib")]
    assert drawing == []


@pytest.mark.parametrize("prefix", ["yaml", "jsonschema", "bench_matrix.matrix", "bench_matrix.scenarios",
                                    "bench_matrix.report", "bench_matrix.registry"])
def test_the_plugin_api_loads_only_the_plugin_contract(prefix: str):
    loaded = subprocess.run([sys.executable, "-c", "import sys, bench_matrix.plugin; print(*sys.modules)"],
                            capture_output=True, text=True, check=True).stdout.split()
    assert [name for name in loaded if name == prefix or name.startswith(prefix + ".")] == []

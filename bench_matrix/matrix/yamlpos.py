"""YAML loading (safe) that remembers the line of every key and item, for located error messages."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import yaml

from bench_matrix.errors import MatrixError

Path_ = tuple[str | int, ...]


def load_with_lines(path: Path) -> tuple[Any, dict[Path_, int]]:
    """Parse `path` with the safe loader; return the data and a map from key path to 1-based line."""
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise MatrixError([f"{path}: file not found"]) from None
    except (OSError, UnicodeDecodeError) as exc:
        raise MatrixError([f"{path}: cannot read: {exc}"]) from None
    try:
        node = yaml.compose(text, Loader=yaml.SafeLoader)
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f"{path}:{mark.line + 1}" if mark else str(path)
        problem = getattr(exc, "problem", None) or str(exc)
        raise MatrixError([f"{where}: not valid YAML: {problem}"]) from None
    if node is None:
        raise MatrixError([f"{path}: the file is empty; a matrix needs at least 'models', 'dataset' and 'axes'"])
    lines: dict[Path_, int] = {(): node.start_mark.line + 1}
    problems: list[str] = []
    data = _convert(node, (), lines, problems, path)
    if problems:
        raise MatrixError(problems)
    return data, lines


PLAIN_TAGS = {"tag:yaml.org,2002:map", "tag:yaml.org,2002:seq"}


def _convert(node: yaml.Node, at: Path_, lines: dict[Path_, int], problems: list[str], path: Path) -> Any:
    if not isinstance(node, yaml.ScalarNode) and node.tag not in PLAIN_TAGS:
        problems.append(f"{path}:{node.start_mark.line + 1}: {format_path(at)}: the tag {node.tag} is not "
                        f"allowed; matrix files are plain YAML (mappings, lists, strings, numbers, booleans)")
        return None
    if isinstance(node, yaml.MappingNode):
        out: dict[str, Any] = {}
        for key_node, value_node in node.value:
            line = key_node.start_mark.line + 1
            if not isinstance(key_node, yaml.ScalarNode):
                problems.append(f"{path}:{line}: {format_path(at)}: keys must be plain names")
                continue
            key = key_node.value
            if key in out:
                problems.append(f"{path}:{line}: {format_path(at + (key,))}: duplicate key '{key}'")
                continue
            lines[at + (key,)] = line
            out[key] = _convert(value_node, at + (key,), lines, problems, path)
        return out
    if isinstance(node, yaml.SequenceNode):
        items = []
        for index, item in enumerate(node.value):
            lines[at + (index,)] = item.start_mark.line + 1
            items.append(_convert(item, at + (index,), lines, problems, path))
        return items
    loader = yaml.SafeLoader("")
    try:
        return loader.construct_object(node, deep=True)
    except yaml.YAMLError:
        problems.append(f"{path}:{node.start_mark.line + 1}: {format_path(at)}: the tag {node.tag} is not "
                        f"allowed; matrix files are plain YAML (mappings, lists, strings, numbers, booleans)")
        return None
    finally:
        loader.dispose()


def format_path(at: Path_) -> str:
    """('models', 0, 'name') -> 'models[0].name'."""
    text = ""
    for part in at:
        text += f"[{part}]" if isinstance(part, int) else (f".{part}" if text else str(part))
    return text or "(top level)"

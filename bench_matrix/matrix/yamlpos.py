"""YAML loading (safe) that remembers the line of every key and item, for located error messages."""

from __future__ import annotations

import difflib
import sys
from pathlib import Path
from typing import Any

import yaml

from bench_matrix.errors import MatrixError, UserError
from bench_matrix.workspace import open_regular

Path_ = tuple[str | int, ...]

MAX_BYTES = 1 << 20  # a matrix file is a few kB; this bounds parse time and memory
MAX_DEPTH = 50  # nesting levels (a matrix needs fewer than 10); keeps PyYAML's recursive composer safe
MAX_VALUES = 100_000  # keys, items and scalars after aliases are expanded: bounds an alias bomb
PLAIN_TAGS = {"tag:yaml.org,2002:map", "tag:yaml.org,2002:seq"}
COLLECTION_STARTS = (yaml.MappingStartEvent, yaml.SequenceStartEvent)
COLLECTION_ENDS = (yaml.MappingEndEvent, yaml.SequenceEndEvent)


class Lines(dict):
    """Key path -> 1-based line; `aliases`: each alias's key path -> its line (the paths under an alias have
    the lines of the value it names)."""

    def __init__(self) -> None:
        super().__init__()
        self.aliases: dict[Path_, int] = {}


def load_with_lines(path: Path) -> tuple[Any, Lines]:
    """Parse `path` with the safe loader; return the data and the line of every key path."""
    text = _read_text(path)
    try:
        _check_depth(text, path)  # the event parser is iterative; the composer below recurses per level
        composer = _Composer(text)
        node = composer.get_single_node()
    except yaml.YAMLError as exc:
        raise MatrixError([_syntax_problem(path, text, exc)]) from None
    if node is None:
        raise MatrixError([f"{path}: the file is empty; a matrix needs at least 'models', 'dataset' and "
                           f"'axes'"])
    converter = _Converter(path, composer.aliases)
    data = converter.convert(node, (), 0)
    if converter.problems:
        raise MatrixError(converter.problems)
    return data, converter.lines


def _read_text(path: Path) -> str:
    """The file's text; a located MatrixError for anything but a readable UTF-8 regular file of sane size."""
    try:
        with open_regular(path) as file:
            raw = file.read(MAX_BYTES + 1)
    except FileNotFoundError:
        raise MatrixError([f"{path}: file not found"]) from None
    except UserError as exc:
        raise MatrixError([f"{exc}; give the path of a YAML matrix file"]) from None
    except (OSError, ValueError) as exc:
        why = getattr(exc, "strerror", None) or exc
        raise MatrixError([f"{path}: cannot read the matrix file: {why}"]) from None
    if len(raw) > MAX_BYTES:
        raise MatrixError([f"{path}: the file is larger than a matrix file can be; limit {MAX_BYTES} bytes "
                           f"(1 MiB; a matrix is a few kB of YAML)"])
    try:
        return raw.decode("utf-8")
    except UnicodeDecodeError as exc:
        line, column = raw.count(b"\n", 0, exc.start) + 1, exc.start - raw.rfind(b"\n", 0, exc.start)
        raise MatrixError([f"{path}:{line}: the file is not UTF-8 text (byte 0x{raw[exc.start]:02x} at "
                           f"column {column}); save it as UTF-8"]) from None


def _check_depth(text: str, path: Path) -> None:
    depth = 0
    for event in yaml.parse(text, Loader=yaml.SafeLoader):
        if isinstance(event, COLLECTION_STARTS):
            depth += 1
            if depth > MAX_DEPTH:
                raise MatrixError([f"{path}:{event.start_mark.line + 1}: nesting too deep: more than "
                                   f"{MAX_DEPTH} levels of mappings and lists; limit {MAX_DEPTH}"])
        elif isinstance(event, COLLECTION_ENDS):
            depth -= 1


def _syntax_problem(path: Path, text: str, exc: yaml.YAMLError) -> str:
    """'file:line: not valid YAML: problem (context that started at line N, column M)'."""
    if isinstance(exc, yaml.reader.ReaderError):
        line = text.count("\n", 0, exc.position) + 1
        return (f"{path}:{line}: not valid YAML: the character #x{exc.character:04x} is not allowed "
                f"(only printable characters are)")
    mark = getattr(exc, "problem_mark", None)
    where = f"{path}:{mark.line + 1}" if mark else str(path)
    problem = getattr(exc, "problem", None) or str(exc)
    message = f"{where}: not valid YAML: {problem}"
    context, start = getattr(exc, "context", None), getattr(exc, "context_mark", None)
    if start is not None and mark is not None and ("end of stream" in problem or "<stream end>" in problem):
        return _unclosed(path, context or "while parsing the construct", start, mark)
    if start is not None:
        message += (f" ({context or 'the construct'} that started at line {start.line + 1}, "
                    f"column {start.column + 1})")
    elif mark is not None:
        message += f" (column {mark.column + 1})"
    return message


def _unclosed(path: Path, context: str, start: yaml.Mark, end: yaml.Mark) -> str:
    """At the line where the construct the file ends in starts: the end of the file is not the mistake."""
    what = context.removeprefix("while scanning ").removeprefix("while parsing ")
    return (f"{path}:{start.line + 1}: not valid YAML: {what} that starts here (column {start.column + 1}) "
            f"is never closed: the file ends first (line {end.line + 1})")


class _Composer(yaml.SafeLoader):
    """The safe loader's node graph, and the line of each alias by its place: (its parent node's id, its index
    or its key node's id); the graph itself puts the named value there, with the anchor's lines."""

    def __init__(self, text: str):
        super().__init__(text)
        self.aliases: dict[tuple[int, int | tuple], int] = {}

    def compose_node(self, parent: yaml.Node | None, index: Any) -> yaml.Node:
        if self.check_event(yaml.AliasEvent) and index is not None:
            self.aliases[place(parent, index)] = self.peek_event().start_mark.line + 1
        return super().compose_node(parent, index)


def place(parent: yaml.Node | None, index: int | yaml.Node) -> tuple[int, int | tuple]:
    return id(parent), index if isinstance(index, int) else ("key", id(index))


class _Converter:
    """Node graph to plain data with a line per key path; refuses tags, cycles and runaway alias expansion."""

    def __init__(self, path: Path, aliases: dict[tuple[int, int | tuple], int]):
        self.path, self.lines, self.problems, self.aliases = path, Lines(), [], aliases
        self.values, self.active = 0, set()
        self.scalars = yaml.SafeLoader("")

    def convert(self, node: yaml.Node, at: Path_, depth: int, alias: int | None = None) -> Any:
        if alias is not None:  # the value named, where the alias stands
            self.lines[at] = self.lines.aliases[at] = alias
        self.lines.setdefault(at, node.start_mark.line + 1)
        self.values += 1
        if self.values > MAX_VALUES or depth > MAX_DEPTH:  # located at the alias expanded
            what, limit = ((f"{MAX_VALUES} values", MAX_VALUES) if self.values > MAX_VALUES else
                           (f"{MAX_DEPTH} levels", MAX_DEPTH))
            line = self.lines[self._expanding(at)]
            raise MatrixError([f"{self.path}:{line}: {format_path(at[:1])}: aliases expand this to more than "
                               f"{what}: aliases/nesting too deep; limit {limit}"])
        if id(node) in self.active:
            self.problems.append(f"{self._where(node, at)}: a recursive alias (it refers to a mapping or "
                                 f"list that contains it); matrix files cannot contain cycles")
            return None
        if not isinstance(node, yaml.ScalarNode) and node.tag not in PLAIN_TAGS:
            return self._refuse_tag(node, at)
        if isinstance(node, yaml.ScalarNode):
            return self._scalar(node, at)
        self.active.add(id(node))
        try:
            if isinstance(node, yaml.MappingNode):
                return self._mapping(node, at, depth)
            return [self.convert(item, at + (i,), depth + 1, self.aliases.get(place(node, i)))
                    for i, item in enumerate(node.value)]
        finally:
            self.active.discard(id(node))

    def _mapping(self, node: yaml.MappingNode, at: Path_, depth: int) -> dict[str, Any]:
        out: dict[str, Any] = {}
        for key_node, value_node in node.value:
            line = key_node.start_mark.line + 1
            if not isinstance(key_node, yaml.ScalarNode):
                self.problems.append(f"{self.path}:{line}: {format_path(at)}: keys must be plain names")
                continue
            key = key_node.value
            if not self._is_unicode(key, key_node, at + (key,)):
                continue
            if key in out:
                self.problems.append(f"{self.path}:{line}: {format_path(at + (key,))}: duplicate key '{key}'")
                continue
            self.lines[at + (key,)] = line
            alias = self.aliases.get(place(node, key_node))
            out[key] = self.convert(value_node, at + (key,), depth + 1, alias)
        return out

    def _scalar(self, node: yaml.ScalarNode, at: Path_) -> Any:
        try:
            value = self.scalars.construct_object(node, deep=True)
        except yaml.YAMLError:
            return self._refuse_tag(node, at)
        except ValueError:  # Python refuses to convert integers of more than 4300 digits
            self.problems.append(f"{self._where(node, at)}: a number of {len(node.value)} characters is too "
                                 f"long to read; limit {sys.get_int_max_str_digits()} digits")
            return None
        return value if not isinstance(value, str) or self._is_unicode(value, node, at) else None

    def _is_unicode(self, text: str, node: yaml.Node, at: Path_) -> bool:
        """False, with a problem, for a string holding a lone surrogate (an escape such as \\ud800)."""
        try:
            text.encode("utf-8")
            return True
        except UnicodeEncodeError as exc:
            self.problems.append(f"{self._where(node, at)}: {text!r} holds {text[exc.start]!r}, which is not "
                                 f"a character (a lone surrogate); write the character itself")
            return False

    def _refuse_tag(self, node: yaml.Node, at: Path_) -> None:
        self.problems.append(f"{self._where(node, at)}: the tag {node.tag} is not allowed; matrix files are "
                             f"plain YAML (mappings, lists, strings, numbers, booleans)")

    def _expanding(self, at: Path_) -> Path_:
        """The first alias on the key path `at` (whose expansion runs away), else its top-level key."""
        return min((p for p in self.lines.aliases if at[:len(p)] == p), key=len, default=at[:1])

    def _where(self, node: yaml.Node, at: Path_) -> str:
        return f"{self.path}:{self.lines.get(at, node.start_mark.line + 1)}: {format_path(at)}"


def format_path(at: Path_) -> str:
    """('models', 0, 'name') -> 'models[0].name'."""
    text = ""
    for part in at:
        text += f"[{part}]" if isinstance(part, int) else (f".{part}" if text else str(part))
    return text or "(top level)"


def suggest(word: str, allowed: list[str] | tuple[str, ...]) -> str:
    """'; did you mean X?' when a close match exists."""
    close = difflib.get_close_matches(str(word), [str(a) for a in allowed], n=1, cutoff=0.6)
    return f"; did you mean '{close[0]}'?" if close else ""


class Located:
    """Collects problems and warnings as 'file:line: key: message', the line of the nearest key path the file
    has."""

    def __init__(self, path: Path, lines: dict[Path_, int]):
        self.path, self.lines, self.problems, self.warnings = path, lines, [], []
        self.aliases: dict[Path_, int] = getattr(lines, "aliases", {})

    def add(self, at: Path_, message: str) -> None:
        self.problems.append(self.located(at, message))

    def warn(self, at: Path_, message: str) -> None:
        self.warnings.append(self.located(at, message))

    def located(self, at: Path_, message: str) -> str:
        """At the line of `at` (or of the nearest key path above it); within an alias's value, at the alias's
        line, naming the value's own line."""
        probe = at
        while probe not in self.lines and probe:
            probe = probe[:-1]
        line = self.lines.get(probe, 1)
        alias = max((p for p in self.aliases if probe[:len(p)] == p), key=len, default=probe)
        if alias == probe:
            return f"{self.path}:{line}: {format_path(at)}: {message}"
        return (f"{self.path}:{self.aliases[alias]}: {format_path(at)}: {message} (in the value the alias "
                f"there names, at line {line})")

"""Every plugin is found through its entry-point group, built-in or third-party, with one way to load it and
the same errors for a broken one: backends (with their clashes and vocabulary, here), trainers, metrics and
scenarios (each group declared where its base class lives)."""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from functools import cache
from collections.abc import Mapping
from importlib.metadata import EntryPoint, entry_points
from typing import Any

from bench_matrix.backend import Backend
from bench_matrix.named import resolve

ENTRY_POINT_GROUP = "bench_matrix.backends"
OWN_DISTRIBUTION = "bench-matrix"  # registers the built-in backends (the bench_matrix_backends package)


class PluginError(Exception):
    """A registered plugin could not be imported or created, or is not what its group holds."""


class BackendLoadError(PluginError):
    """A registered backend could not be imported or is not a Backend."""


@dataclass(frozen=True)
class Group:
    """An entry-point group: its name, the word for one of its plugins, the class each must be an instance of,
    and the error a broken one raises."""

    name: str
    kind: str
    base: type | str  # or "module:Class", imported when a plugin is loaded (a base in a higher layer)
    error: type[PluginError] = PluginError

    def names(self) -> list[str]:
        """The registered names, sorted."""
        return sorted({ep.name for ep in entry_points(group=self.name)})

    def entry(self, name: str) -> EntryPoint:
        """The (first) registration of `name`."""
        found = [ep for ep in entry_points(group=self.name) if ep.name == name]
        if not found:
            raise self.error(f"no {self.kind} named {name!r} is installed "
                             f"(installed: {', '.join(self.names()) or 'none'})")
        return found[0]

    def load(self, name: str) -> Any:
        """Import and instantiate the plugin registered as `name`."""
        ep = self.entry(name)
        base = resolve(self.base) if isinstance(self.base, str) else self.base
        return _created(_imported(ep, self.kind, self.error), f"{self.kind} {name!r} ({ep.value})", base,
                        self.error)

    def load_all(self) -> tuple[Any, ...]:
        """Every registered plugin, by name."""
        return tuple(self.load(name) for name in self.names())


SCENARIOS = Group("bench_matrix.scenarios", "scenario", "bench_matrix.scenarios.base:Scenario")


@cache
def scenarios() -> tuple[Any, ...]:
    """One instance of each registered scenario (the built-in ones and plugins'), by name: each is selected
    per cell by its own top-level matrix section."""
    return SCENARIOS.load_all()


def _imported(ep: EntryPoint, kind: str, error: type[PluginError]) -> Any:
    """What the entry point names, imported."""
    try:
        return ep.load()
    except Exception as exc:  # a broken plugin must not take the tool down
        raise error(f"{kind} {ep.name!r} ({ep.value}) failed to import: {type(exc).__name__}: {exc}") from exc


def _created(cls: Any, where: str, base: type, error: type[PluginError]) -> Any:
    """An instance of the imported `cls`, which must make a `base`."""
    if not (isinstance(cls, type) and issubclass(cls, base)):
        raise error(f"{where} is not a {base.__module__}.{base.__qualname__} subclass")
    try:
        return cls()
    except Exception as exc:  # e.g. an abstract method left unimplemented
        raise error(f"{where} cannot be created: {type(exc).__name__}: {exc}") from exc


@dataclass(frozen=True)
class BackendEntry:
    """A registered backend before import: name, target, distribution ("NAME VERSION"); `replaced`: the name's
    other registrations its class replaces; `clash`: why unusable (rival distributions, none replacing)."""

    name: str
    value: str
    distribution: str
    replaced: tuple[str, ...] = ()
    clash: str = ""

    @property
    def builtin(self) -> bool:
        """Whether bench-matrix registers it itself."""
        return self.distribution.split(" ", 1)[0] == OWN_DISTRIBUTION


def available() -> dict[str, BackendEntry]:
    """Every registered backend by name, sorted: a name several distributions register is the one whose class
    declares it `replaces` the others, else a clash that cannot be loaded (never a silent pick)."""
    found: dict[str, dict[tuple[str, str], EntryPoint]] = {}
    for ep in sorted(entry_points(group=ENTRY_POINT_GROUP), key=lambda e: e.name):
        found.setdefault(ep.name, {}).setdefault((ep.value, _distribution(ep)), ep)
    return {name: _in_effect(name, registered) for name, registered in found.items()}


def _in_effect(name: str, registered: dict[tuple[str, str], EntryPoint]) -> BackendEntry:
    """The registration of `name` in effect among several (value, distribution): the one declaring it
    replaces the others, else the built-in one (or the first), marked with the clash."""
    entries = sorted((BackendEntry(name, value, distribution) for value, distribution in registered),
                     key=lambda e: (not e.builtin, e.distribution, e.value))  # the built-in one first
    if len(entries) == 1:
        return entries[0]
    replacing = [e for e in entries if _replaces(registered[(e.value, e.distribution)]) == name]
    if len(replacing) == 1:
        return replace(replacing[0], replaced=tuple(e.distribution for e in entries if e is not replacing[0]))
    both = " and ".join(f"{e.distribution} ({e.value})" for e in entries)
    return replace(entries[0], clash=f"backend {name!r} is registered by {both}, and "
                                     f"{'more than one' if replacing else 'none'} of their classes declares "
                                     f"replaces = {name!r}: uninstall one, or declare in the class that "
                                     f"replaces the other `replaces = {name!r}`")


def _replaces(ep: EntryPoint) -> str:
    """The name the registered class declares it replaces ("" when none, or when it cannot be imported)."""
    try:
        declared = getattr(ep.load(), "replaces", "")
    except Exception:  # a broken plugin must not take the tool down; it declares nothing
        return ""
    return declared if isinstance(declared, str) else ""


@dataclass(frozen=True)
class Vocabulary:
    """What installed backends declare: targets and precisions with their backends, backends' options as JSON
    Schema properties, unloadable ones (why); targets in built-ins' order (by name), then plugins' sorted."""

    targets: dict[str, list[str]]
    precisions: dict[str, list[str]]
    options: dict[str, dict[str, Any]]
    broken: dict[str, str] = field(default_factory=dict)


def vocabulary() -> Vocabulary:
    """What every installed backend class declares (imported, not instantiated; a broken one is absent)."""
    targets: dict[str, list[str]] = {}
    precisions: dict[str, list[str]] = {}
    options: dict[str, dict[str, Any]] = {}
    broken: dict[str, str] = {}
    entries = available()
    for name in sorted(entries, key=lambda n: not entries[n].builtin):  # the built-in ones first, by name
        try:
            cls = backend_class(name, entries)
            declared = {"targets": dict.fromkeys(t for s in cls.supports for t in s.targets),
                        "precisions": dict.fromkeys(p for s in cls.supports for p in s.precisions)}
            problem = _options_problem(cls.options)
        except Exception as exc:  # a broken plugin must not take the tool down
            broken[name] = str(exc) if isinstance(exc, BackendLoadError) else f"{type(exc).__name__}: {exc}"
            continue
        if problem:
            broken[name] = f"its options are not a valid JSON Schema: {problem}"
            continue
        for found, values in ((targets, declared["targets"]), (precisions, declared["precisions"])):
            for value in values:
                found.setdefault(value, []).append(name)
        options[name] = dict(cls.options)
    builtin = [t for t, names in targets.items() if any(entries[n].builtin for n in names)]
    ordered = {t: targets[t] for t in builtin + sorted(set(targets) - set(builtin))}
    return Vocabulary(ordered, precisions, options, broken)


def _options_problem(options: Any) -> str | None:
    """Why a backend's `options` declaration is not a mapping of JSON Schemas, or None."""
    import jsonschema

    if not isinstance(options, dict):
        return f"expected a mapping of option name to schema, got {type(options).__name__}"
    try:
        jsonschema.Draft202012Validator.check_schema({"type": "object", "properties": options})
    except jsonschema.SchemaError as exc:
        return exc.message
    return None


def backend_class(name: str, entries: Mapping[str, BackendEntry] | None = None) -> type[Backend]:
    """Import one registered backend's class (`entries`: `available()`'s answer, when the caller has it)."""
    entries = available() if entries is None else entries
    if name not in entries:
        raise BackendLoadError(f"no backend named {name!r} is installed (installed: {', '.join(entries)})")
    if entries[name].clash:
        raise BackendLoadError(entries[name].clash)
    ep = EntryPoint(name, entries[name].value, ENTRY_POINT_GROUP)
    cls = _imported(ep, "backend", BackendLoadError)
    if not (isinstance(cls, type) and issubclass(cls, Backend)):
        raise BackendLoadError(f"backend {name!r} ({ep.value}) is not a "
                               "bench_matrix.backend.Backend subclass")
    return cls


def load_backend(name: str) -> Backend:
    """Import and instantiate one registered backend."""
    cls = backend_class(name)
    where = f"backend {name!r} ({cls.__module__}:{cls.__qualname__})"
    backend = _created(cls, where, Backend, BackendLoadError)
    if backend.name != name:
        raise BackendLoadError(f"backend registered as {name!r} calls itself {backend.name!r}")
    return backend


def _distribution(ep: EntryPoint) -> str:
    dist = ep.dist
    return f"{dist.metadata['Name']} {dist.version}" if dist is not None else "unknown"

"""Backends are found only through the `bench_matrix.backends` entry-point group, built-in or plugin."""

from __future__ import annotations

from dataclasses import dataclass
from importlib.metadata import EntryPoint, entry_points

from bench_matrix.backends.base import Backend

ENTRY_POINT_GROUP = "bench_matrix.backends"


class BackendLoadError(Exception):
    """A registered backend could not be imported or is not a Backend."""


@dataclass(frozen=True)
class BackendEntry:
    """A registered backend before it is imported: its name, target and distribution."""

    name: str
    value: str
    distribution: str


def available() -> dict[str, BackendEntry]:
    """Every registered backend by name (first registration of a name wins, sorted by name)."""
    found: dict[str, BackendEntry] = {}
    for ep in sorted(entry_points(group=ENTRY_POINT_GROUP), key=lambda e: e.name):
        found.setdefault(ep.name, BackendEntry(ep.name, ep.value, _distribution(ep)))
    return found


def load_backend(name: str) -> Backend:
    """Import and instantiate one registered backend."""
    eps = [ep for ep in entry_points(group=ENTRY_POINT_GROUP) if ep.name == name]
    if not eps:
        raise BackendLoadError(f"no backend named {name!r} is installed (installed: {', '.join(available())})")
    ep = eps[0]
    try:
        cls = ep.load()
    except Exception as exc:  # a broken plugin must not take the tool down
        raise BackendLoadError(f"backend {name!r} ({ep.value}) failed to import: {type(exc).__name__}: {exc}") from exc
    if not (isinstance(cls, type) and issubclass(cls, Backend)):
        raise BackendLoadError(f"backend {name!r} ({ep.value}) is not a bench_matrix Backend subclass")
    try:
        backend = cls()
    except Exception as exc:  # e.g. an abstract method left unimplemented
        raise BackendLoadError(f"backend {name!r} ({ep.value}) cannot be created: {type(exc).__name__}: {exc}") from exc
    if backend.name != name:
        raise BackendLoadError(f"backend registered as {name!r} calls itself {backend.name!r}")
    return backend


def _distribution(ep: EntryPoint) -> str:
    dist = ep.dist
    return f"{dist.metadata['Name']} {dist.version}" if dist is not None else "unknown"

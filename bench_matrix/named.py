"""What a 'module:name' reference names (a job's function, a scenario's class), imported when asked for."""

from __future__ import annotations

from importlib import import_module
from typing import Any


def resolve(reference: str) -> Any:
    """The object `reference` ('package.module:name') names, its module imported."""
    module, _, name = reference.partition(":")
    return getattr(import_module(module), name)

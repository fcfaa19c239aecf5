"""The one serialiser of job results at the process boundary: a result to JSON values in the job's process
(`to_json`), and back to its type in the parent (`from_json`)."""

from __future__ import annotations

import base64
import dataclasses
import itertools
import types
import typing
from pathlib import Path
from typing import Any


def to_json(value: Any) -> Any:
    """A result as JSON values: dataclasses as objects, paths as text, bytes as base64, a dict keyed by tuples
    as [key, value] pairs."""
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        return {f.name: to_json(getattr(value, f.name)) for f in dataclasses.fields(value)}
    if isinstance(value, Path):
        return str(value)
    if isinstance(value, bytes):
        return base64.b64encode(value).decode()
    if isinstance(value, (tuple, list)):
        return [to_json(v) for v in value]
    if isinstance(value, dict) and any(isinstance(k, tuple) for k in value):
        return [[to_json(k), to_json(v)] for k, v in value.items()]
    if isinstance(value, dict):
        return {k: to_json(v) for k, v in value.items()}
    return value


def from_json(kind: Any, data: Any) -> Any:
    """The value of type `kind` that `to_json` turned into `data`."""
    origin, args = typing.get_origin(kind), typing.get_args(kind)
    if data is None or kind is Any:
        return data
    if origin in (typing.Union, types.UnionType):
        return from_json(next(a for a in args if a is not type(None)), data)
    if dataclasses.is_dataclass(kind):
        hints = typing.get_type_hints(kind)
        fields = [f.name for f in dataclasses.fields(kind) if f.init]
        return kind(**{name: from_json(hints[name], data[name]) for name in fields})
    if kind is Path:
        return Path(data)
    if kind is bytes:
        return base64.b64decode(data)
    if origin is tuple:
        typed = zip(itertools.repeat(args[0]), data) if args[-1] is Ellipsis else zip(args, data)
        return tuple(from_json(a, v) for a, v in typed)
    if origin is dict and args[0] is not str:
        return {from_json(args[0], k): from_json(args[1], v) for k, v in data}
    if origin is dict:
        return {k: from_json(args[1], v) for k, v in data.items()}
    return data
